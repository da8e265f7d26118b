"""`genreg-bench`: GenReg beside classical baselines on the paper's datasets, one command.

    genreg-bench --suite quick --out runs/bench_quick --threads 2
    genreg-bench --suite smoke --checkpoint /tmp/untrained.pt --out /tmp/bench_smoke
    genreg-bench --ablation pose-solver --datasets modelnet-unseen-clean --max-pairs 20 --out runs/ablation
    genreg-bench --suite partial --out build/bench_partial --object-checkpoint /root/genreg-runs/x/best.pt
    genreg-bench --suite map --out runs/bench_map --threads 2 --pairs 20 --off-map 10

--suite partial: the partial-overlap tables (RPM-Net-style ModelNet40 pairs; kidnapped redkitchen
frame pairs 30, 60 and 90 apart and SUN3D ones 5 and 20 apart, at full resolution) with GenReg +
point-to-point / point-to-plane ICP beside ICP, FPFH + RANSAC + ICP (fast and accurate), KISS-Matcher
+ ICP and small_gicp; --frame-stride subsamples the frames (e.g. 2 for a quicker look). Rows with
GenReg's confidence add its ROC AUC, ECE and confident-wrong count; reliability.png is the
reliability diagram.

--suite map: localisation in a prebuilt map (`genreg_bench.map_suite`): `MapLocalizer` without a guess and
tracking from the pose 2 frames earlier, FPFH + RANSAC + ICP and KISS-Matcher + point-to-plane (gated on
their fitness) on held-out scans of maps fused from redkitchen validation and SUN3D frames. --pairs sets
the on-map scans per map (default 20), --off-map the off-map scans per map (default 10), --frame-stride the
pixel stride of scans and maps (default 4), --map-voxel the maps' voxel, --combined-map adds the redkitchen +
SUN3D-1 map 10 m apart, --methods picks among genreg, genreg-tracking, fpfh+ransac+icp and
kiss-matcher+p2plane. It writes report.md, results.json and a map_<map>.png per map (map_redkitchen.png,
map_sun3d-1.png, ...).

--ablation runs the ablations on the suite's datasets instead of the method comparison
(pose-solver: PDSAC against Open3D RANSAC on the same generated correspondences; backbone: GenReg
object models with different backbones on the object datasets: by default the shipped pointmixer
`modelnet40` and dgcnn `modelnet40_dgcnn`, or --backbones NAME=CHECKPOINT ...; --paper-checkpoint adds
a row for a checkpoint of the paper's own generator).
Checkpoints: objects (ModelNet40) use --object-checkpoint (default: genreg_core.config.OBJECT_MODEL), scenes
(7-Scenes, SUN3D) use --scene-checkpoint (default: SCENE_MODEL); --checkpoint sets both. A missing
checkpoint skips the GenReg methods on those datasets with a message. Threads are fixed before torch
and Open3D load: OMP_NUM_THREADS (Open3D), torch intra-op threads, small_gicp workers, and
OMP_WAIT_POLICY=PASSIVE unless set (spinning OpenMP workers starve on a shared 2-core machine).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from genreg_core.config import OBJECT_MODEL, SCENE_MODEL

ABLATIONS = ("pose-solver", "backbone")  # `ablation.ABLATIONS` (not imported here: torch loads after threads)
SUITE_NAMES = ("smoke", "quick", "full", "partial", "map")  # `datasets.SUITES` (likewise), and the map suite


def configure_threads(threads: int) -> None:
    """Pin every thread pool to `threads`; call before importing torch / Open3D for OpenMP to see it."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    torch.set_num_threads(threads)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set, or parallel work already ran in this process
        pass


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="genreg-bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", default="quick", choices=SUITE_NAMES)
    p.add_argument("--out", required=True, help="output folder (report.md, results.json, PNGs: reliability.png among them)")
    p.add_argument("--threads", type=int, default=2, help="CPU threads for every library (default 2)")
    p.add_argument("--checkpoint", help="GenReg checkpoint (name or path) for objects and scenes")
    p.add_argument("--object-checkpoint", help=f"checkpoint for ModelNet40 datasets (default {OBJECT_MODEL})")
    p.add_argument("--scene-checkpoint", help=f"checkpoint for 7-Scenes/SUN3D datasets (default {SCENE_MODEL})")
    p.add_argument("--datasets", nargs="+", help="only these datasets of the suite")
    p.add_argument("--methods", nargs="+", help="only these methods")
    p.add_argument("--max-pairs", type=int, help="at most this many pairs per dataset")
    p.add_argument("--pairs", type=int, help="this many pairs per dataset (evenly spread; all when it holds fewer) "
                   "instead of the suite's counts; --suite map: on-map scans per map (default 20)")
    p.add_argument("--off-map", type=int, default=10, help="--suite map: off-map scans per map (default 10)")
    p.add_argument("--mirrored", type=int, default=10, help="--suite map: mirrored on-map scans per map (no pose "
                   "is right; default 10)")
    p.add_argument("--map-voxel", type=float, default=0.02, help="--suite map: the maps' voxel, m (default 0.02)")
    p.add_argument("--combined-map", action="store_true",
                   help="--suite map: also the redkitchen + SUN3D-1 map, 10 m apart")
    p.add_argument("--object-points", type=int, default=512, help="points per ModelNet40 cloud (default 512)")
    p.add_argument("--fmr-points", type=int, default=1024, help="points per FMR-style cloud (default 1024)")
    p.add_argument("--frame-stride", type=int,
                   help="real frames: every N-th pixel (default: the suite's, 4 for smoke and map, else 1 = full "
                        "resolution)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--confidence-thresholds", type=float, nargs="+", default=[0.5, 0.9],
                   help="report the success rate above/below these confidences (default 0.5 0.9)")
    p.add_argument("--data-root", help="dataset folder (default: GENREG_DATA or ../shared/data)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--from-json", help="re-render the report of an earlier run's results.json (no registration)")
    p.add_argument("--ablation", nargs="+", choices=ABLATIONS,
                   help="run these ablations on the suite's datasets instead of the method comparison")
    p.add_argument("--backbones", nargs="+", metavar="NAME=CHECKPOINT",
                   help="backbone ablation rows (default: pointmixer=modelnet40 dgcnn=modelnet40_dgcnn, the shipped "
                        "models; scripts/ablation_backbone.sh passes its retrained runs/abl_<name>/last.pt)")
    p.add_argument("--paper-checkpoint", metavar="CHECKPOINT",
                   help="backbone ablation: add a row 'paper' for this checkpoint of the paper's generator")
    args = p.parse_args(argv)
    if args.backbones and any("=" not in b for b in args.backbones):
        p.error("--backbones takes NAME=CHECKPOINT pairs")
    if args.suite == "map" and (args.ablation or args.from_json or args.datasets):
        p.error("--suite map takes no --ablation, --from-json or --datasets")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configure_threads(args.threads)
    from genreg_core.memory import retain_freed_memory

    retain_freed_memory()
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # RANSAC's mutual-filter notes
    if args.suite == "map":
        from genreg_bench.map_suite import run_map_suite

        return run_map_suite(args)
    from genreg_bench.datasets import DATASETS, OBJECT, SCENE, SUITES, BenchOptions
    from genreg_bench.methods import DEFAULT_CHECKPOINTS
    from genreg_bench.report import load_run, write_report
    from genreg_bench.runner import run_benchmark

    if args.datasets and set(args.datasets) - set(DATASETS):
        print(f"unknown datasets {sorted(set(args.datasets) - set(DATASETS))}; known: {list(DATASETS)}",
              file=sys.stderr)
        return 2
    checkpoints = {
        OBJECT: args.object_checkpoint or args.checkpoint or DEFAULT_CHECKPOINTS[OBJECT],
        SCENE: args.scene_checkpoint or args.checkpoint or DEFAULT_CHECKPOINTS[SCENE],
    }
    options = BenchOptions(object_points=args.object_points, fmr_points=args.fmr_points, seed=args.seed,
                           threads=args.threads, data_root=args.data_root, frame_stride=args.frame_stride)
    if args.from_json:
        paths = write_report(load_run(args.from_json), args.out, args.confidence_thresholds)
        print(paths["markdown"].read_text())
        return 0
    t0 = time.perf_counter()
    def log(message: str) -> None:
        print(message, file=sys.stderr)

    try:
        if args.ablation:
            from genreg_bench.ablation import DEFAULT_BACKBONES, run_ablations

            backbones = dict(b.split("=", 1) for b in args.backbones) if args.backbones else dict(DEFAULT_BACKBONES)
            if args.paper_checkpoint:
                backbones["paper"] = args.paper_checkpoint
            run = run_ablations(args.suite, checkpoints, options, args.ablation, args.datasets, args.max_pairs,
                                progress=not args.no_progress, log=log, backbones=backbones)
        else:
            suite = args.suite if args.pairs is None else SUITES[args.suite].with_pairs(args.suite, args.pairs)
            run = run_benchmark(suite, checkpoints, options, args.methods, args.datasets, args.max_pairs,
                                progress=not args.no_progress, log=log)
    except ValueError as exc:
        print(f"genreg-bench: {exc}", file=sys.stderr)
        return 2
    run.meta["wall_seconds"] = time.perf_counter() - t0
    paths = write_report(run, args.out, args.confidence_thresholds)
    print(paths["markdown"].read_text())
    what = f"{args.suite} suite" + (f", ablation {' '.join(args.ablation)}" if args.ablation else "")
    print(f"{what}: {run.meta['wall_seconds']:.0f} s with {args.threads} threads; wrote "
          + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
