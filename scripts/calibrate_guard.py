#!/usr/bin/env python3
"""Choose the refinement guard's threshold (`RefineConfig.guard_below`) on training pairs, through the API.

    python scripts/calibrate_guard.py --pairs 150 --threads 2

ModelNet40 seen categories, *train* split (never the benchmark's test pairs), seed 1, two kinds of pairs:
the paper's partial variant (target without its 20 % largest-x points, N=512) with the object model, and
RPM-Net-style partial-to-partial crops with `modelnet40_partial`. Each pair is registered by
`Registrar.register` with point-to-point refinement and each `guard_below` of THRESHOLDS (0: no guard),
so the guard is the API's own rule: it runs when the overlap score of the refined estimate
(`score.overlap_score` of its fitness, tight fitness and inlier ratio) is below `guard_below`, and its wide
ICP from identity wins when it puts more source points within one target spacing of the target
(`score.TIGHT_SPACINGS`); the result's `start` is then "guard". Per setting: mean / median RE,
success (RE < 5 deg), the share of pairs on which the guard runs (its cost; from the unguarded result's
scores) and the share on which it switches.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from genreg_core.config import OBJECT_MODEL  # no torch: threads are set before it loads

THRESHOLDS = (0.0, 0.3, 0.4, 0.5, 1.0)
KINDS = (("partial", OBJECT_MODEL), ("crop", "modelnet40_partial"))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=150)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    from genreg_bench.cli import configure_threads

    configure_threads(args.threads)
    import numpy as np
    from tqdm import tqdm

    from genreg_bench.datasets import RPMNetPairs
    from genreg_core.config import RefineConfig, RegistrationConfig
    from genreg_core.data import ModelNetPairs, load_modelnet40
    from genreg_core.metrics import transform_errors
    from genreg_core.registration import Registrar
    from genreg_core.score import overlap_score

    def config(guard_below: float) -> RegistrationConfig:
        return RegistrationConfig(seed=0, refine=RefineConfig(method="point_to_point", guard_below=guard_below))

    shapes = load_modelnet40("train", "seen")
    for kind, checkpoint in KINDS:
        plain = Registrar.from_checkpoint(checkpoint, config(0.0))
        registrars = {th: Registrar(plain.model, config(th), plain.calibration) if th else plain for th in THRESHOLDS}
        pairs = (RPMNetPairs(shapes, seed=1) if kind == "crop"
                 else ModelNetPairs(shapes, plain.num_points, kind, seed=1))
        re = {th: [] for th in THRESHOLDS}
        switched = {th: [] for th in THRESHOLDS}
        trigger = []  # the score the guard compares with guard_below (the unguarded result's: no guess given)
        for i in tqdm(np.random.default_rng(1).choice(len(pairs), args.pairs, replace=False), unit="pair",
                      desc=kind):
            item = pairs[int(i)]
            T_gt = np.asarray(item["transform"], dtype=np.float64)
            for th, registrar in registrars.items():
                result = registrar.register(item["source"], item["target"])
                re[th].append(transform_errors(result.transformation, T_gt)[0])
                switched[th].append(result.start == "guard")
                if th == 0.0:
                    trigger.append(overlap_score(result.fitness, result.tight_fitness, result.inlier_ratio))
        trigger_a = np.array(trigger)
        print(f"\n{args.pairs} {kind} pairs, ModelNet40 train split (seen), checkpoint {checkpoint}, point-to-point"
              "\n\n| guard_below | RE mean (deg) | RE median (deg) | success | guard runs | switches |"
              "\n|---|---|---|---|---|---|")
        for th in THRESHOLDS:
            chosen = np.array(re[th])
            print(f"| {th:g} | {chosen.mean():.2f} | {np.median(chosen):.2f} | {np.mean(chosen < 5):.0%} "
                  f"| {np.mean(trigger_a < th):.0%} | {np.mean(switched[th]):.0%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
