"""Choose the node's `min_confidence` (results below it are rejected) on training pairs.

Registers redkitchen training frame pairs (frames 0-799; gaps 10-60; the source moved by a further random
"kidnap" motion of up to 45 deg and 0.5 m, so that some registrations fail) with the scene model and the
scene preset `config.SCENE_REGISTRATION` (the node's scene settings; --method swaps its refinement method),
and prints, per threshold, the share of successes kept and of failures rejected
(success: RE < 2 deg and TE < 5 cm), plus the ROC AUC of the confidence. The default is the largest
multiple of 0.05 at least 0.05 below the lowest confidence of a training success: it rejects no training
success, with a margin for data the model never saw, which scores lower.

    python scripts/calibrate_min_confidence.py --pairs 60
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from tqdm import tqdm

from genreg_bench.report import roc_auc
from genreg_core.config import SCENE_REGISTRATION
from genreg_core.data import RGBDSequence
from genreg_core.geometry import apply_transform, kidnap_motion
from genreg_core.metrics import transform_errors
from genreg_core.registration import Registrar


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=60)
    p.add_argument("--method", default=SCENE_REGISTRATION.refine.method,
                   help="refinement method (default: the scene preset's)")
    p.add_argument("--stride", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    scene = replace(SCENE_REGISTRATION, refine=replace(SCENE_REGISTRATION.refine, method=args.method))
    reg = Registrar.from_checkpoint("7scenes", scene)
    seq = RGBDSequence.redkitchen()
    conf, ok = [], []
    for _ in tqdm(range(args.pairs), leave=False):
        gap = int(rng.integers(10, 61))
        i = int(rng.integers(0, 800 - gap))
        src, tgt = seq.points(i + gap, stride=args.stride), seq.points(i, stride=args.stride)
        K = kidnap_motion(rng, src.mean(axis=0))
        result = reg.register(apply_transform(K, src), tgt)
        re, te = transform_errors(result.transformation, seq.relative_pose(i + gap, i) @ np.linalg.inv(K))
        conf.append(result.confidence)
        ok.append(re < 2.0 and te < 0.05)
    conf, ok = np.array(conf), np.array(ok)
    print(f"{args.method}, {len(ok)} training pairs, success {ok.mean():.0%}, confidence ROC AUC {roc_auc(conf, ok) or float('nan'):.3f}")
    print("| min_confidence | successes kept | failures rejected |")
    print("|---|---|---|")
    for t in np.round(np.arange(0.0, 0.65, 0.05), 2):
        kept = (conf[ok] >= t).mean() if ok.any() else float("nan")
        rejected = (conf[~ok] < t).mean() if (~ok).any() else float("nan")
        print(f"| {t:.2f} | {kept:.0%} | {rejected:.0%} |")
    lowest = float(conf[ok].min()) if ok.any() else 0.0
    best = max(0.0, np.floor((lowest - 0.05) / 0.05) * 0.05)
    print(f"lowest confidence of a success {lowest:.3f}; chosen min_confidence: {best:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
