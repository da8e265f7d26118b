#!/usr/bin/env python3
"""Choose the refinement guard (`refine.guard_below` and the spacing its fitness is compared at) on
training pairs.

    python scripts/calibrate_guard.py --pairs 150 --threads 2

ModelNet40 seen categories, *train* split (never the benchmark's test pairs), seed 1, two kinds of pairs:
the paper's partial variant (target without its 20 % largest-x points, N=512) with the object model, and
RPM-Net-style partial-to-partial crops with `modelnet40_partial`. Per pair: the API without the guard
(RE, confidence, fitness) and the guard's own candidate, computed as the API does: the pair prepared by
`Registrar.prepare`, `refine.guard_icp` on its refinement clouds, `score.overlap_fitness` of both
candidates at `spacings` target spacings (the API's fitness uses `score.FITNESS_SPACINGS` = 3). The
guard runs when the confidence is below `guard_below` and takes its candidate when that fitness is
higher. Per setting: mean / median RE, success (RE < 5 deg), the share of pairs on which the guard runs
(its cost) and the share on which it switches.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from genreg_core.config import OBJECT_MODEL  # no torch: threads are set before it loads

THRESHOLDS = (0.0, 0.3, 0.4, 0.5, 1.0)
SPACINGS = (3.0, 1.0, 0.6)
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
    from genreg_core.prepare import model_frame_config
    from genreg_core.refine import guard_icp
    from genreg_core.registration import Registrar
    from genreg_core.score import FITNESS_SPACINGS, fitness_distance, overlap_fitness

    refine = RefineConfig(method="point_to_point", guard_below=0.0)
    shapes = load_modelnet40("train", "seen")
    for kind, checkpoint in KINDS:
        registrar = Registrar.from_checkpoint(checkpoint, RegistrationConfig(seed=0, refine=refine))
        pairs = (RPMNetPairs(shapes, seed=1) if kind == "crop"
                 else ModelNetPairs(shapes, registrar.num_points, kind, seed=1))
        rows = []
        for i in tqdm(np.random.default_rng(1).choice(len(pairs), args.pairs, replace=False), unit="pair",
                      desc=kind):
            item = pairs[int(i)]
            T_gt = np.asarray(item["transform"], dtype=np.float64)
            plain = registrar.register(item["source"], item["target"])
            prep = registrar.prepare(item["source"], item["target"])  # the API's frame and refinement clouds
            T_plain = prep.to_normalized(plain.transformation)
            T_guard = guard_icp(prep.dense_src, prep.dense_tgt, model_frame_config(registrar.config, prep.scale).refine)
            spacing = fitness_distance(prep.dense_tgt) / FITNESS_SPACINGS
            fits = [[overlap_fitness(prep.dense_src, prep.dense_tgt, T, s * spacing)[0] for s in SPACINGS]
                    for T in (T_plain, T_guard)]
            rows.append((transform_errors(plain.transformation, T_gt)[0], plain.confidence,
                         transform_errors(prep.to_input_units(T_guard), T_gt)[0], *fits[0], *fits[1]))
        data = np.array(rows)
        re, conf, re_guard = data[:, 0], data[:, 1], data[:, 2]
        fit_plain, fit_guard = data[:, 3: 3 + len(SPACINGS)], data[:, 3 + len(SPACINGS):]
        print(f"\n{args.pairs} {kind} pairs, ModelNet40 train split (seen), checkpoint {checkpoint}, point-to-point"
              "\n\n| guard_below | spacings | RE mean (deg) | RE median (deg) | success | guard runs | switches |"
              "\n|---|---|---|---|---|---|---|")
        for th in THRESHOLDS:
            for j, s in enumerate(SPACINGS):
                switch = (conf < th) & (fit_guard[:, j] > fit_plain[:, j])
                chosen = np.where(switch, re_guard, re)
                print(f"| {th:g} | {s:g} | {chosen.mean():.2f} | {np.median(chosen):.2f} | {np.mean(chosen < 5):.0%} "
                      f"| {np.mean(conf < th):.0%} | {switch.mean():.0%} |")
                if th == 0.0:
                    break  # no guard: the spacing does not matter
    return 0


if __name__ == "__main__":
    sys.exit(main())
