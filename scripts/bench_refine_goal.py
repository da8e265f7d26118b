#!/usr/bin/env python3
"""The refinement goal, measured: on the partial protocol, GenReg + refinement against
FPFH + RANSAC + ICP in mean RE, and in time (goal: at most 1/5 of FPFH + RANSAC + ICP's).

    python scripts/bench_refine_goal.py --pairs 100 --threads 2 --batch 16

Pairs: ModelNet40 seen (test split) and unseen categories, partial variant, N=512, seed 0: the pairs of
`genreg-bench --suite full` with the same --max-pairs. In one process and thread setting, per pair:
- `fpfh+ransac+icp`: the benchmark's baseline (Open3D, unit-box settings), wall time per pair;
- `genreg+icp`: `Registrar.register` with point-to-point refinement and its guard, batch 1 (latency);
- `genreg+icp batched`: `Registrar.register_many` on batches of --batch pairs (throughput: wall time of
  the whole call divided by its pairs; PDSAC draws differ from batch 1, so the accuracy is its own).
Prints RE mean / median (deg), success (RE < 5 deg, TE < 0.1) and ms per pair (median for batch 1,
mean over batches for throughput), and the time ratio to FPFH + RANSAC + ICP.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from genreg_core.config import OBJECT_MODEL  # no torch: threads are set before it loads

DATASETS = ("modelnet-seen-partial", "modelnet-unseen-partial")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--checkpoint", default=OBJECT_MODEL)
    args = p.parse_args()
    from genreg_bench.cli import configure_threads

    configure_threads(args.threads)
    import numpy as np
    from tqdm import tqdm

    from genreg_bench.baselines import BaselineParams, fpfh_ransac_icp
    from genreg_bench.datasets import BenchOptions, plan_suite
    from genreg_bench.runner import thread_report
    from genreg_core.config import RefineConfig, RegistrationConfig
    from genreg_core.metrics import transform_errors
    from genreg_core.registration import Registrar

    _, _, plan = plan_suite("full", BenchOptions(object_points=512, seed=0, threads=args.threads), DATASETS, args.pairs)
    registrar = Registrar.from_checkpoint(
        args.checkpoint, RegistrationConfig(seed=0, refine=RefineConfig(method="point_to_point")))
    params = BaselineParams.unit_box(args.threads)
    th = thread_report(args.threads)
    print(f"threads {args.threads} (torch {th['torch']}, OMP_NUM_THREADS={th['OMP_NUM_THREADS']}); "
          f"{args.pairs} pairs per dataset, checkpoint {args.checkpoint}, batch {args.batch}\n")
    print("| dataset | method | RE mean (deg) | RE median (deg) | success | ms per pair | time / FPFH+RANSAC+ICP | "
          "guard won |")
    print("|---|---|---|---|---|---|---|---|")
    for spec, pairs, indices in plan:
        items = [pairs[i] for i in indices]
        clouds = [(it["source"].astype(np.float64), it["target"].astype(np.float64)) for it in items]
        truths = [np.asarray(it["transform"], dtype=np.float64) for it in items]
        registrar.register(*clouds[0])  # warm-up
        fpfh_ransac_icp(*clouds[0], params)
        rows: dict[str, tuple[list, list, list]] = {}
        baseline = rows.setdefault("fpfh+ransac+icp", ([], [], []))
        single = rows.setdefault("genreg+icp", ([], [], []))
        for (src, tgt), T_gt in tqdm(list(zip(clouds, truths, strict=True)), desc=spec.name, unit="pair"):
            T, seconds = fpfh_ransac_icp(src, tgt, params)
            baseline[0].append(transform_errors(T, T_gt))
            baseline[1].append(seconds)
            t0 = time.perf_counter()
            res = registrar.register(src, tgt)
            single[1].append(time.perf_counter() - t0)
            single[0].append(transform_errors(res.transformation, T_gt))
            single[2].append(res.start == "guard")
        batched = rows.setdefault(f"genreg+icp batched ({args.batch})", ([], [], []))
        for k in range(0, len(clouds), args.batch):
            chunk = clouds[k : k + args.batch]
            t0 = time.perf_counter()
            results = registrar.register_many(chunk)
            batched[1].extend([(time.perf_counter() - t0) / len(chunk)] * len(chunk))
            batched[0].extend(transform_errors(r.transformation, T) for r, T in zip(results, truths[k:], strict=False))
            batched[2].extend(r.start == "guard" for r in results)
        base_ms = 1e3 * float(np.median(baseline[1]))
        for name, (errors, seconds, guard) in rows.items():
            re = np.array([e[0] for e in errors])
            te = np.array([e[1] for e in errors])
            ms = 1e3 * (float(np.mean(seconds)) if "batched" in name else float(np.median(seconds)))
            won = f"{np.mean(guard):.0%}" if guard else "–"
            print(f"| {spec.name} | {name} | {re.mean():.2f} | {np.median(re):.2f} | "
                  f"{np.mean((re < 5) & (te < 0.1)):.0%} | {ms:.1f} | {ms / base_ms:.2f} | {won} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
