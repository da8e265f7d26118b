#!/usr/bin/env python3
"""Speed benchmark of the core (issue 2, "Speed"): ms per registration beside Open3D baselines.

    python scripts/bench_speed.py --threads 2 --repeats 20

For N = 512, 1024 and 2048: an untrained model of the shipped `modelnet40` architecture at that N (speed
does not depend on the weights; `--checkpoint` times a trained model, and its architecture, at its own N
instead)
registers the same pairs as Open3D point-to-point ICP (from identity) and FPFH + RANSAC, in this run,
batch 1, with the given thread count; medians over the pairs. Pairs: ModelNet40 unseen categories
(unit box, paper transform) for N <= 1024 (the shapes have 1024 points), 7-Scenes redkitchen
validation FMR-style pairs (unit box) for N = 2048. GenReg's time is split into preprocessing
(validation, normalisation, resampling), network, PDSAC and postprocessing (fitness, mapping back).
Goal printed beside it: <= 30 ms at N = 1024. Then a real 7-Scenes pair at full resolution (~300k
points per cloud, metres) end to end, goal < 1 s.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

GOAL_MS_N1024 = 30.0
GOAL_S_FRAME = 1.0


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=20, help="pairs per N (median over them)")
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    p.add_argument("--frame-repeats", type=int, default=3, help="repeats of the 300k-point frame pair")
    p.add_argument("--batch", type=int, default=16, help="batched network + PDSAC throughput (0: skip)")
    p.add_argument("--checkpoint", help="time this checkpoint (name or path) at its own N instead of untrained "
                   "models of the shipped architecture at --sizes")
    p.add_argument("--json", help="also write the figures to this JSON file")
    return p.parse_args()


def main() -> int:
    args = parse_args()
    from genreg_core.bench.cli import configure_threads

    configure_threads(args.threads)  # before Open3D loads

    from dataclasses import replace

    import numpy as np
    import torch

    from genreg_core.bench.baselines import BaselineParams, fpfh_ransac, icp_point_to_point
    from genreg_core.bench.methods import measure_throughput
    from genreg_core.bench.runner import thread_report
    from genreg_core.checkpoint import load_checkpoint
    from genreg_core.config import RegistrationConfig
    from genreg_core.data import REDKITCHEN_VAL_FRAMES, FMRPairs, ModelNetPairs, RGBDSequence, load_modelnet40
    from genreg_core.model import build_model
    from genreg_core.registration import Registrar

    def med(xs: list[float]) -> float:  # seconds -> median ms
        return 1e3 * float(np.median(xs))

    threads = thread_report(args.threads)
    load_start = os.getloadavg()[0]
    print(f"threads: {args.threads} (torch {threads['torch']}, OMP_NUM_THREADS={threads['OMP_NUM_THREADS']}, "
          f"OMP_WAIT_POLICY={threads['OMP_WAIT_POLICY']}); {args.repeats} pairs per N, batch 1, medians; "
          f"1-min load average {load_start:.1f} on {os.cpu_count()} CPUs (other jobs included)")

    def registrar(n: int) -> Registrar:
        if args.checkpoint:
            return Registrar.from_checkpoint(args.checkpoint, RegistrationConfig(seed=0))
        torch.manual_seed(0)
        shipped = load_checkpoint("modelnet40")[0].config
        return Registrar(build_model(replace(shipped, num_points=n)), RegistrationConfig(seed=0))

    if args.checkpoint:
        args.sizes = [registrar(0).num_points]

    unit, metric = BaselineParams.unit_box(args.threads), BaselineParams.metric_scene(args.threads)
    redkitchen = RGBDSequence.redkitchen()
    rows = []
    for n in args.sizes:
        if n <= 1024:
            pairs, source = ModelNetPairs(load_modelnet40("test", "unseen"), n, seed=0), "ModelNet40 unseen"
        else:
            pairs, source = FMRPairs(redkitchen, REDKITCHEN_VAL_FRAMES, n, seed=0), "redkitchen FMR"
        indices = np.linspace(0, len(pairs) - 1, args.repeats).astype(int).tolist()
        reg = registrar(n)
        first = pairs[indices[0]]
        reg.register(first["source"], first["target"])  # warm-up
        icp_point_to_point(first["source"], first["target"], unit)
        stages: dict[str, list[float]] = {}
        icp, ransac = [], []
        for i in indices:
            item = pairs[i]
            for k, v in reg.register(item["source"], item["target"]).timings.items():
                stages.setdefault(k, []).append(v)
            icp.append(icp_point_to_point(item["source"], item["target"], unit)[1])
            ransac.append(fpfh_ransac(item["source"], item["target"], unit)[1])
        row = {"N": n, "pairs": source, **{f"{k}_ms": med(v) for k, v in stages.items()},
               "icp_ms": med(icp), "fpfh_ransac_ms": med(ransac)}
        if args.batch:
            row["batched_ms_per_pair"] = measure_throughput(reg, pairs, indices, args.batch)["ms_per_pair_batched"]
        rows.append(row)

    head = ("| N | pairs | GenReg total | preprocess | network | PDSAC | post | ICP p2p | FPFH+RANSAC | "
            "GenReg/ICP | GenReg/RANSAC | net+PDSAC batched | goal |")
    print("\n" + head + "\n" + "|---" * 13 + "|")
    for r in rows:
        goal = ""
        if r["N"] == 1024:
            gap = r["total_ms"] - GOAL_MS_N1024
            goal = f"<= {GOAL_MS_N1024:.0f} ms: " + ("met" if gap <= 0 else f"missed by {gap:.1f} ms")
        batched = f"{r['batched_ms_per_pair']:.1f} (x{args.batch})" if "batched_ms_per_pair" in r else "–"
        print(f"| {r['N']} | {r['pairs']} | {r['total_ms']:.1f} | {r['preprocess_ms']:.1f} | {r['network_ms']:.1f} | "
              f"{r['pdsac_ms']:.1f} | {r['postprocess_ms']:.1f} | {r['icp_ms']:.1f} | {r['fpfh_ransac_ms']:.1f} | "
              f"{r['total_ms'] / r['icp_ms']:.1f}x | {r['total_ms'] / r['fpfh_ransac_ms']:.2f}x | {batched} | {goal} |")
    weights = f"checkpoint {args.checkpoint}" if args.checkpoint else "untrained weights of the shipped architecture"
    print(f"(ms; GenReg = network + PDSAC end to end through Registrar.register, {weights})")

    # A real frame pair at full resolution, metres: the API resamples to N; baselines downsample themselves.
    n_frame = 1024 if 1024 in args.sizes else args.sizes[0]
    reg = registrar(n_frame)
    src, tgt = redkitchen.points(810), redkitchen.points(800)
    reg.register(src, tgt)  # warm-up
    frame: dict[str, list[float]] = {}
    for _ in range(args.frame_repeats):
        for k, v in reg.register(src, tgt).timings.items():
            frame.setdefault(k, []).append(v)
    f_icp = [icp_point_to_point(src, tgt, metric)[1] for _ in range(args.frame_repeats)]
    f_ransac = [fpfh_ransac(src, tgt, metric)[1] for _ in range(args.frame_repeats)]
    total = med(frame["total"])
    split = ", ".join(f"{k} {med(v):.0f}" for k, v in frame.items() if k != "total")
    print(f"\n7-Scenes redkitchen frames 810 -> 800: {len(src)} / {len(tgt)} points, GenReg N={n_frame}: "
          f"{total:.0f} ms end to end ({split}); goal < {GOAL_S_FRAME * 1e3:.0f} ms: "
          f"{'met' if total < GOAL_S_FRAME * 1e3 else 'missed'}. Same pair: ICP p2p (2 cm voxels) {med(f_icp):.0f} ms, "
          f"FPFH+RANSAC (5 cm voxels) {med(f_ransac):.0f} ms.")
    print(f"1-min load average at the end: {os.getloadavg()[0]:.1f}")
    if args.json:
        frame_row = {"points": [len(src), len(tgt)], "N": n_frame, **{f"{k}_ms": med(v) for k, v in frame.items()},
                     "icp_ms": med(f_icp), "fpfh_ransac_ms": med(f_ransac)}
        load = {"start": load_start, "end": os.getloadavg()[0]}
        Path(args.json).write_text(json.dumps({"threads": threads, "load_average": load, "rows": rows,
                                               "frame_pair": frame_row}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
