#!/usr/bin/env python3
"""Choose `refine.guard_below` (the refinement guard's confidence threshold) on training-split pairs.

    python scripts/calibrate_guard.py --pairs 150 --threads 2

ModelNet40 seen categories, *train* split (never the benchmark's test pairs), partial variant at N=512,
seed 1. Per pair the API runs twice: guard off (guard_below 0: RE and confidence) and guard always on
(guard_below 1: RE and whether the initial guess won). The guard runs exactly when the unguarded
confidence is below the threshold, so each threshold's outcome follows: the table shows the mean / median
RE, the share of pairs on which the guard would run (its cost) and the share on which the prior wins.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

THRESHOLDS = (0.0, 0.1, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6, 1.0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=150)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--checkpoint", default="modelnet40")
    args = p.parse_args()
    from genreg_core.bench.cli import configure_threads

    configure_threads(args.threads)
    import numpy as np
    from tqdm import tqdm

    from genreg_core.config import RefineConfig, RegistrationConfig
    from genreg_core.data import ModelNetPairs, load_modelnet40
    from genreg_core.metrics import transform_errors
    from genreg_core.registration import Registrar

    refine = RefineConfig(method="point_to_point")
    never = Registrar.from_checkpoint(args.checkpoint, RegistrationConfig(seed=0, refine=replace(refine, guard_below=0.0)))
    always = Registrar(never.model, RegistrationConfig(seed=0, refine=replace(refine, guard_below=1.0)))
    pairs = ModelNetPairs(load_modelnet40("train", "seen"), never.num_points, "partial", seed=1)
    rows = []
    for i in tqdm(np.random.default_rng(1).choice(len(pairs), args.pairs, replace=False), unit="pair"):
        item = pairs[int(i)]
        T_gt = np.asarray(item["transform"], dtype=np.float64)
        plain, guarded = (r.register(item["source"], item["target"]) for r in (never, always))
        rows.append((transform_errors(plain.transformation, T_gt)[0], plain.confidence,
                     transform_errors(guarded.transformation, T_gt)[0], guarded.start == "initial_guess"))
    re, conf, re_guarded, prior_won = np.array(rows).T
    print(f"{args.pairs} partial pairs, ModelNet40 train split (seen), N={never.num_points}, checkpoint "
          f"{args.checkpoint}\n\n| guard_below | RE mean (deg) | RE median (deg) | guard runs | prior wins |\n|---|---|---|---|---|")
    for th in THRESHOLDS:
        runs = conf < th
        wins = runs & (prior_won > 0)
        chosen = np.where(runs, re_guarded, re)
        print(f"| {th:g} | {chosen.mean():.2f} | {np.median(chosen):.2f} | {runs.mean():.0%} | {wins.mean():.0%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
