#!/usr/bin/env python3
"""Speed benchmark of the core: the registration API beside classical baselines, against its speed goals.

    python scripts/bench_speed.py --threads 1 2

Each thread count runs in its own subprocess (OpenMP reads its thread count once, before Open3D loads):
torch intra-op threads, OMP_NUM_THREADS (Open3D, the scores' k-d tree) and small_gicp workers all get it,
OMP_WAIT_POLICY=PASSIVE. Every figure is a median in ms, batch 1 unless stated; baselines include their
own downsampling, normals and features.
- Real pair: 7-Scenes redkitchen frames 810 -> 800 at full resolution (~270k points each, metres). The API
  with the shipped `7scenes` model and the scene preset's PDSAC (`config.SCENE_REGISTRATION`), without
  refinement, with point-to-plane refinement and with the preset's GICP (the speed goals' settings), split into its
  stages (`RegistrationResult.timings`), beside Open3D point-to-plane ICP from identity (2.5 cm voxels),
  small_gicp GICP (2.5 cm voxels) and FPFH + RANSAC + ICP (5 cm feature voxels).
- Objects: the shipped object models at N=512 on ModelNet40 unseen-category pairs (unit box), beside FPFH +
  RANSAC on the same pairs: `modelnet40_dgcnn` (the default object model since commit 7f8b38a, 2026-12-02),
  `modelnet40_partial` (partial overlap) and `modelnet40` (the mixer model, the default before).
- The speed goals (since commit 1cce558, 2026-11-24): API / point-to-plane ICP <= 0.25 without refinement and <= 0.35 with it
  (point-to-plane, or the scene preset's GICP), object
  model / FPFH + RANSAC <= 0.4, network + PDSAC <= 10 ms at N=512, preprocess + postprocess <= 4 ms on
  the real pair.
- Per-stage cost (`registration.STAGES`): the scene preset on kidnapped redkitchen pairs (frames 800-999, 10
  and 60 apart, a random rotation and shift each) and the default object model on ModelNet40 pairs, split into
  the confident common case (a first answer at or above `pdsac.modes_below`: no modes, no more passes) and the
  unsure case; medians per stage, and the tight stage of the scene preset's refinement measured as the
  preset's refinement against the same without it on the real pair.
- Throughput: `register_many`, pairs per second at batch 1, 8 and 16 (object model on the ModelNet40 pairs,
  scene model on copies of the real pair), and network + PDSAC alone (`measure_throughput`).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

if TYPE_CHECKING:
    from genreg_bench.baselines import BaselineFn, BaselineParams
    from genreg_core.registration import Registrar

SCENE_FRAMES = (810, 800)  # redkitchen source -> target
SCENE_VOXEL = 0.025  # m: ICP and small_gicp downsampling
OBJECT_MODELS = ("modelnet40_dgcnn", "modelnet40_partial", "modelnet40")
OBJECT_POINTS = 512
SPLIT = ("prepare", "network", "pdsac", "refine", "result")  # the stages of the API rows (the rest: `verify` etc.)
COST_PAIRS = 24  # kidnapped redkitchen pairs (gaps 10 and 60) and ModelNet40 pairs of the per-stage cost table
Figures = dict[str, Any]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts, one subprocess each")
    p.add_argument("--repeats", type=int, default=9, help="API runs on the real pair (median)")
    p.add_argument("--baseline-repeats", type=int, default=3, help="baseline runs on the real pair (median)")
    p.add_argument("--object-pairs", type=int, default=20, help="ModelNet40 pairs (median over them)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 8, 16], help="register_many batch sizes")
    p.add_argument("--cost-pairs", type=int, default=COST_PAIRS, help="pairs per per-stage cost table")
    p.add_argument("--scene-checkpoint", default="7scenes", help="scene model for the real pair (name or file)")
    p.add_argument("--object-models", nargs="+", default=list(OBJECT_MODELS), help="object models (names or files)")
    p.add_argument("--json", help="also write every figure to this JSON file")
    p.add_argument("--default-malloc", action="store_true", help="leave glibc's malloc as it is (without "
                   "genreg_core.memory.retain_freed_memory, which genreg's entry points call)")
    p.add_argument("--worker-out", help=argparse.SUPPRESS)  # internal: measure one thread count, write JSON
    return p.parse_args(argv)


# --- measuring (worker process) ---------------------------------------------------------------------------

def median_ms(seconds: Sequence[float]) -> float:
    return 1e3 * statistics.median(seconds)


def api_ms(registrar: Registrar, pairs: Sequence[tuple[Any, Any]]) -> dict[str, float]:
    """Median wall time of `register` ('wall') and of each stage of its timings over the pairs (warm-up first)."""
    registrar.register(*pairs[0])
    wall: list[float] = []
    stages: dict[str, list[float]] = {}
    for source, target in pairs:
        t0 = time.perf_counter()
        result = registrar.register(source, target)
        wall.append(time.perf_counter() - t0)
        for stage, seconds in result.timings.items():
            stages.setdefault(stage, []).append(seconds)
    return {"wall": median_ms(wall), **{stage: median_ms(s) for stage, s in stages.items()}}


def baseline_ms(fn: BaselineFn, pairs: Sequence[tuple[Any, Any]], params: BaselineParams) -> float:
    """Median of the baseline's own wall time over the pairs (warm-up first)."""
    fn(*pairs[0], params)
    return median_ms([fn(source, target, params)[1] for source, target in pairs])


def throughput(registrar: Registrar, pairs: Sequence[tuple[Any, Any]], batches: Sequence[int]) -> dict[str, float]:
    """Pairs per second of `register_many` at each batch size: the same max(batches) pairs (cycled) in
    batches of that size, one pass after a warm-up batch."""
    work = [pairs[k % len(pairs)] for k in range(max(batches))]
    rates = {}
    for batch in batches:
        registrar.register_many(work[:batch])
        t0 = time.perf_counter()
        for start in range(0, len(work), batch):
            registrar.register_many(work[start:start + batch])
        rates[str(batch)] = len(work) / (time.perf_counter() - t0)
    return rates


def scene_figures(args: argparse.Namespace, threads: int) -> Figures:
    """The real pair: the API (plain, point-to-plane) and the baselines, and register_many throughput."""
    from dataclasses import replace

    from genreg_bench.baselines import (
        BaselineParams,
        fpfh_ransac_icp,
        icp_point_to_plane,
        small_gicp_gicp,
    )
    from genreg_core.config import SCENE_REGISTRATION, RefineConfig
    from genreg_core.data import RGBDSequence
    from genreg_core.registration import Registrar

    sequence = RGBDSequence.redkitchen()
    pair = (sequence.points(SCENE_FRAMES[0]), sequence.points(SCENE_FRAMES[1]))
    scene = replace(SCENE_REGISTRATION, seed=0)
    plain = Registrar.from_checkpoint(args.scene_checkpoint, replace(scene, refine=RefineConfig()))
    p2plane = Registrar(plain.model, replace(scene, refine=RefineConfig(method="point_to_plane")), plain.calibration)
    gicp = Registrar(plain.model, scene, plain.calibration)  # the scene preset: GICP and its tight stage
    params = replace(BaselineParams.metric_scene(threads), icp_voxel_size=SCENE_VOXEL, gicp_voxel_size=SCENE_VOXEL)
    baseline_pairs = [pair] * args.baseline_repeats
    return {
        "checkpoint": args.scene_checkpoint,
        "points": [len(pair[0]), len(pair[1])],
        "api": api_ms(plain, [pair] * args.repeats),
        "api_p2plane": api_ms(p2plane, [pair] * args.repeats),
        "api_gicp": api_ms(gicp, [pair] * args.repeats),
        "icp_p2plane": baseline_ms(icp_point_to_plane, baseline_pairs, params),
        "small_gicp": baseline_ms(small_gicp_gicp, baseline_pairs, params),
        "fpfh_ransac_icp": baseline_ms(fpfh_ransac_icp, baseline_pairs, params),
        "api_gicp_one_stage": api_ms(Registrar(plain.model, replace(scene, refine=replace(scene.refine, fine_fraction=1.0)),
                                               plain.calibration), [pair] * args.repeats),
        "throughput": throughput(plain, [pair], args.batches),
        "cost": stage_costs(gicp, kidnapped_pairs(args.cost_pairs)),
    }


def kidnapped_pairs(count: int) -> list[tuple[Any, Any]]:
    """`count` kidnapped redkitchen validation pairs, half 10 and half 60 frames apart (`genreg-bench`'s kidnap
    pairs, seed 0), at pixel stride 2."""
    import numpy as np

    from genreg_bench.datasets import BenchOptions, kidnap_pairs

    pairs = []
    for gap in (10, 60):
        dataset = kidnap_pairs(["redkitchen"], gap)(BenchOptions(frame_stride=2))
        picks = np.linspace(0, len(dataset) - 1, count // 2).astype(int)
        pairs += [(dataset[int(i)]["source"], dataset[int(i)]["target"]) for i in picks]
    return pairs


def stage_costs(registrar: Registrar, pairs: Sequence[tuple[Any, Any]]) -> dict[str, Any]:
    """Median ms per stage (`registration.STAGES`, 0 where a stage did not run) and of the total, for the confident
    pairs (the first answer at or above `pdsac.modes_below`: neither modes nor more passes ran) and the unsure
    ones, with their counts."""
    from genreg_core.registration import STAGES

    registrar.register(*pairs[0])
    cases: dict[str, list[dict[str, float]]] = {"confident": [], "unsure": []}
    for source, target in pairs:
        timings = registrar.register(source, target).timings
        cases["unsure" if "modes" in timings or "passes" in timings else "confident"].append(timings)
    return {case: {"pairs": len(runs), **{stage: median_ms([r.get(stage, 0.0) for r in runs]) if runs else 0.0
                                          for stage in (*STAGES, "total")}} for case, runs in cases.items()}


def object_figures(args: argparse.Namespace, threads: int) -> Figures:
    """ModelNet40 unseen pairs: each object model through the API, FPFH + RANSAC, and throughputs."""
    import numpy as np

    from genreg_bench.baselines import BaselineParams, fpfh_ransac
    from genreg_bench.methods import measure_throughput
    from genreg_core.config import RegistrationConfig
    from genreg_core.data import ModelNetPairs, load_modelnet40
    from genreg_core.registration import Registrar

    dataset = ModelNetPairs(load_modelnet40("test", "unseen"), OBJECT_POINTS, seed=0)
    indices = np.linspace(0, len(dataset) - 1, args.object_pairs).astype(int).tolist()
    pairs = [(dataset[i]["source"], dataset[i]["target"]) for i in indices]
    figures: Figures = {"pairs": len(pairs), "fpfh_ransac": baseline_ms(fpfh_ransac, pairs,
                                                                        BaselineParams.unit_box(threads))}
    for name in args.object_models:
        registrar = Registrar.from_checkpoint(name, RegistrationConfig(seed=0), num_points=OBJECT_POINTS)
        figures[name] = api_ms(registrar, pairs)
        figures[name]["throughput"] = throughput(registrar, pairs, args.batches)
        batched = measure_throughput(registrar, dataset, indices, max(args.batches))
        figures[name]["net_pdsac_batch1"] = batched["ms_batch1"]
        figures[name]["net_pdsac_batched"] = batched["ms_per_pair_batched"]
        if name == args.object_models[0]:
            figures["cost"] = stage_costs(registrar, [(dataset[i]["source"], dataset[i]["target"]) for i in
                                                      np.linspace(0, len(dataset) - 1, args.cost_pairs).astype(int)])
    return figures


def measure(args: argparse.Namespace) -> Figures:
    """Every figure at one thread count (this process's only one)."""
    threads = args.threads[0]
    from genreg_bench.cli import configure_threads

    configure_threads(threads)  # before torch and Open3D run anything
    if not args.default_malloc:
        from genreg_core.memory import retain_freed_memory

        retain_freed_memory()
    import open3d as o3d

    from genreg_bench.runner import thread_report

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    load = os.getloadavg()[0]
    figures = {"threads": thread_report(threads), "scene": scene_figures(args, threads),
               "objects": object_figures(args, threads)}
    figures["load_average"] = [load, os.getloadavg()[0]]
    return figures


def run_workers(args: argparse.Namespace) -> dict[int, Figures]:
    """One subprocess per thread count; their figures by thread count."""
    options = ["--repeats", str(args.repeats), "--baseline-repeats", str(args.baseline_repeats),
               "--object-pairs", str(args.object_pairs), "--cost-pairs", str(args.cost_pairs), "--batches", *map(str, args.batches),
               "--scene-checkpoint", args.scene_checkpoint, "--object-models", *args.object_models,
               *(["--default-malloc"] if args.default_malloc else [])]
    results = {}
    for threads in args.threads:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "figures.json"
            subprocess.run([sys.executable, __file__, *options, "--threads", str(threads), "--worker-out", str(out)],
                           check=True)
            results[threads] = json.loads(out.read_text())
    return results


# --- reporting (parent process) ---------------------------------------------------------------------------

def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A markdown table; floats with one decimal (two below 1)."""
    def cell(v: object) -> str:
        return (f"{v:.2f}" if abs(v) < 1 else f"{v:.1f}") if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    return "\n".join(lines + ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows])


def stage_split(api: dict[str, float]) -> str:
    """'prepare / network / PDSAC / refine / result' ms of one API row."""
    return " / ".join(f"{api.get(stage, 0.0):.1f}" for stage in SPLIT)


def print_scene(results: dict[int, Figures]) -> None:
    threads = list(results)
    scenes = [results[t]["scene"] for t in threads]
    points = scenes[0]["points"]
    print(f"\nReal pair: redkitchen {SCENE_FRAMES[0]} -> {SCENE_FRAMES[1]}, {points[0]} / {points[1]} points (m), "
          f"{scenes[0]['checkpoint']} model; ms (API: wall time of `register`, and its stages prepare / network / PDSAC / refine "
          "/ result)")
    rows = [
        ["API, no refinement", *(s["api"]["wall"] for s in scenes), *(stage_split(s["api"]) for s in scenes)],
        ["API + point-to-plane", *(s["api_p2plane"]["wall"] for s in scenes),
         *(stage_split(s["api_p2plane"]) for s in scenes)],
        ["API + GICP (scene preset)", *(s["api_gicp"]["wall"] for s in scenes), *(stage_split(s["api_gicp"]) for s in scenes)],
        ["Open3D p2plane ICP (2.5 cm voxels)", *(s["icp_p2plane"] for s in scenes), *("" for _ in scenes)],
        ["small_gicp GICP (2.5 cm voxels)", *(s["small_gicp"] for s in scenes), *("" for _ in scenes)],
        ["FPFH + RANSAC + ICP (5 cm)", *(s["fpfh_ransac_icp"] for s in scenes), *("" for _ in scenes)],
    ]
    print(table(["method", *(f"{t} thr ms" for t in threads), *(f"{t} thr stages" for t in threads)], rows))
    for t, s in zip(threads, scenes, strict=True):
        for key, label in (("api", "no refinement"), ("api_p2plane", "point-to-plane"), ("api_gicp", "GICP")):
            total = s[key]["total"]
            shares = ", ".join(f"{stage} {100 * v / total:.0f} %" for stage, v in s[key].items()
                               if stage not in ("wall", "total"))
            print(f"stage shares, {t} thread(s), {label}: {shares}")
        tight = s["api_gicp"]["refine"] - s["api_gicp_one_stage"]["refine"]
        print(f"tight stage of the scene preset's GICP, {t} thread(s): {tight:.1f} ms (refine {s['api_gicp']['refine']:.1f} "
              f"with it, {s['api_gicp_one_stage']['refine']:.1f} without)")


def print_costs(results: dict[int, Figures]) -> None:
    """The per-stage cost table: confident and unsure pairs of the scene preset and of the default object model."""
    from genreg_core.registration import STAGES

    for t, figures in results.items():
        print(f"\nPer-stage cost, {t} thread(s), median ms per stage (0: the stage did not run); confident: the first "
              "answer at or above pdsac.modes_below (no modes, no more passes)")
        rows = []
        for label, cost in ((f"scene preset, kidnapped redkitchen ({figures['scene']['checkpoint']})", figures["scene"]["cost"]),
                            (f"objects, ModelNet40 unseen ({object_models(results)[0]})", figures["objects"]["cost"])):
            for case in ("confident", "unsure"):
                c = cost[case]
                rows.append([label, case, c["pairs"], *(c[stage] for stage in (*STAGES, "total"))])
        print(table(["pairs", "case", "n", *STAGES, "total"], rows))


def object_models(results: dict[int, Figures]) -> list[str]:
    """The object models measured (every key of the objects' figures that is a model's)."""
    objects = next(iter(results.values()))["objects"]
    return [k for k, v in objects.items() if isinstance(v, dict) and "wall" in v]


def print_objects(results: dict[int, Figures]) -> None:
    threads = list(results)
    objects = [results[t]["objects"] for t in threads]
    print(f"\nObjects: ModelNet40 unseen categories, N={OBJECT_POINTS}, {objects[0]['pairs']} pairs (unit box); ms")
    rows = []
    for name in object_models(results):
        rows.append([f"API {name}", *(o[name]["wall"] for o in objects), *(stage_split(o[name]) for o in objects),
                     *(f"{o[name]['net_pdsac_batched']:.1f}" for o in objects)])
    rows.append(["FPFH + RANSAC", *(o["fpfh_ransac"] for o in objects), *("" for _ in objects), *("" for _ in objects)])
    print(table(["method", *(f"{t} thr ms" for t in threads), *(f"{t} thr stages" for t in threads),
                 *(f"{t} thr net+PDSAC batched/pair" for t in threads)], rows))


def goals(figures: Figures) -> list[tuple[str, float, float]]:
    """(goal, value, limit) of the speed goals at one thread count; the value must be <= the limit."""
    scene, objects = figures["scene"], figures["objects"]
    rows = [
        ("API / p2plane ICP, no refinement", scene["api"]["wall"] / scene["icp_p2plane"], 0.25),
        ("API + p2plane / p2plane ICP", scene["api_p2plane"]["wall"] / scene["icp_p2plane"], 0.35),
        ("API + GICP (scene preset) / p2plane ICP", scene["api_gicp"]["wall"] / scene["icp_p2plane"], 0.35),
    ]
    for name in object_models({0: figures}):
        rows.append((f"{name} / FPFH + RANSAC", objects[name]["wall"] / objects["fpfh_ransac"], 0.4))
        rows.append((f"{name} network + PDSAC, ms", objects[name]["network"] + objects[name]["pdsac"], 10.0))
    api = scene["api"]
    rows.append(("real pair prepare + result, ms", api["prepare"] + api["result"], 4.0))
    return rows


def print_goals(results: dict[int, Figures]) -> None:
    threads = list(results)
    per_thread = [goals(results[t]) for t in threads]
    rows = []
    for k, (label, _, limit) in enumerate(per_thread[0]):
        values = [g[k][1] for g in per_thread]
        verdicts = ["met" if v <= limit else f"missed (x{v / limit:.1f})" for v in values]
        rows.append([label, *(f"{v:.2f}" for v in values), f"<= {limit:g}", *verdicts])
    print("\nSpeed goals")
    print(table(["goal", *(f"{t} thr" for t in threads), "goal", *(f"{t} thr" for t in threads)], rows))


def print_throughput(results: dict[int, Figures]) -> None:
    threads = list(results)
    batches = list(results[threads[0]]["scene"]["throughput"])
    rows = []
    for t in threads:
        objects, scene = results[t]["objects"], results[t]["scene"]
        for name in object_models(results):
            rows.append([f"{name}, ModelNet40 pairs", t, *(objects[name]["throughput"][b] for b in batches)])
        rows.append([f"{scene['checkpoint']}, the real pair", t, *(scene["throughput"][b] for b in batches)])
    print("\nregister_many throughput, pairs per second (no refinement)")
    print(table(["model, pairs", "threads", *(f"batch {b}" for b in batches)], rows))


def print_header(results: dict[int, Figures], load_start: float) -> None:
    settings = "; ".join(f"{t}: torch {r['threads']['torch']}, OMP_NUM_THREADS={r['threads']['OMP_NUM_THREADS']}, "
                         f"OMP_WAIT_POLICY={r['threads']['OMP_WAIT_POLICY']}" for t, r in results.items())
    print(f"threads ({settings}); one subprocess per thread count; medians; 1-min load average {load_start:.2f} "
          f"at the start, {os.getloadavg()[0]:.2f} at the end, on {os.cpu_count()} CPUs (other jobs included)")


def report(results: dict[int, Figures], load_start: float) -> None:
    sections: tuple[Callable[[dict[int, Figures]], None], ...] = (print_scene, print_objects, print_costs,
                                                                  print_goals, print_throughput)
    print_header(results, load_start)
    for section in sections:
        section(results)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.worker_out:
        Path(args.worker_out).write_text(json.dumps(measure(args)))
        return 0
    load_start = os.getloadavg()[0]
    results = run_workers(args)
    report(results, load_start)
    if args.json:
        Path(args.json).write_text(json.dumps({str(t): r for t, r in results.items()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
