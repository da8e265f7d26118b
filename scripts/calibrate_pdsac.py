#!/usr/bin/env python3
"""Choose PDSAC's inference settings (hypotheses, minimal-set size, local optimisation) on training pairs.

    python scripts/calibrate_pdsac.py --settings 512x4x1x- 512x3x4x- 512x3x4x0.5,0.25 --kinds crop partial clean

A setting is HYPOTHESESxSAMPLE_SIZExLOCAL_CANDIDATES[xTIGHTENING] (`PDSACConfig`; TIGHTENING: the
`refit_tightening` fractions, comma-separated, "-" for none; default the config's). Kinds, never
benchmark pairs:
- crop: RPM-Net-style crops of the ModelNet40 *train* split (seen categories), 100 pairs (seed 2, or
  `--crop-seed`), each
  registered with PDSAC seeds 0 and 1, `modelnet40_partial`;
- partial / clean: the paper's one-side partial and clean pairs of the same split, 100 pairs (seed 1,
  picks seed 3), `modelnet40`;
- kidnap30 / kidnap60: redkitchen *training* frames (0-799) 30 / 60 apart, the source moved by a kidnap
  motion, 40 pairs (seeds 7 / 8), pixel stride 2, `7scenes` (success: RE < 2 deg and TE < 5 cm);
- gap10: redkitchen training frames 10 apart, no kidnap, 40 pairs (seed 11), stride 2, `7scenes`.
Per setting: RE mean / median and success alone and refined (point-to-point; on scenes the scene preset
`config.SCENE_REGISTRATION`'s refinement, GICP with 20 iterations, the node's).
`--checkpoints` replaces a kind's checkpoint by each of these in turn (names or files): the same table
then chooses among training snapshots, on training pairs.
The MODEL_CARD "PDSAC settings" table is this script's output (its "before" rows: the code before
`local_candidates`, commit 4aa431f).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

KINDS = ("crop", "partial", "clean", "kidnap30", "kidnap60", "gap10")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--settings", nargs="+", default=["512x3x4"])
    p.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--checkpoints", nargs="+", help="checkpoints to compare in place of each kind's own")
    p.add_argument("--scene-pairs", type=int, default=40, help="kidnap30 / kidnap60 / gap10: pairs (the first 40 "
                   "are the default set)")
    p.add_argument("--num-points", type=int, help="N for the checkpoints (statistics-free models run at any N)")
    p.add_argument("--crop-seed", type=int, default=2, help="crop: the pairs' seed (another set of training crops)")
    args = p.parse_args()
    from genreg_bench.cli import configure_threads

    configure_threads(args.threads)
    import numpy as np
    from tqdm import tqdm

    from genreg_bench.datasets import RPMNetPairs
    from genreg_core.config import SCENE_REGISTRATION, PDSACConfig, RefineConfig, RegistrationConfig
    from genreg_core.data import ModelNetPairs, RGBDSequence, load_modelnet40
    from genreg_core.geometry import apply_transform, kidnap_motion
    from genreg_core.metrics import transform_errors
    from genreg_core.registration import Registrar

    def pairs_of(kind: str) -> tuple[str, list[tuple], tuple[int, ...]]:
        """(checkpoint, [(source, target, T_gt)], PDSAC seeds) for a kind."""
        if kind == "gap10":
            seq, rng = RGBDSequence.redkitchen(), np.random.default_rng(11)
            starts = [int(rng.integers(0, 790)) for _ in range(args.scene_pairs)]
            return "7scenes", [(seq.points(i + 10, stride=2), seq.points(i, stride=2), seq.relative_pose(i + 10, i))
                               for i in starts], (0,)
        if kind.startswith("kidnap"):
            gap, seq = int(kind[6:]), RGBDSequence.redkitchen()
            rng = np.random.default_rng(7 if gap == 30 else 8)
            items = []
            for _ in range(args.scene_pairs):
                i = int(rng.integers(0, 800 - gap))
                src, tgt = seq.points(i + gap, stride=2), seq.points(i, stride=2)
                K = kidnap_motion(rng, src.mean(axis=0))
                items.append((apply_transform(K, src), tgt, seq.relative_pose(i + gap, i) @ np.linalg.inv(K)))
            return "7scenes", items, (0,)
        shapes = load_modelnet40("train", "seen")
        if kind == "crop":
            crops = RPMNetPairs(shapes, seed=args.crop_seed)
            picks = np.random.default_rng(args.crop_seed).choice(len(crops), 100, replace=False)
            return "modelnet40_partial", [(it["source"], it["target"], it["transform"]) for it in
                                          (crops[int(i)] for i in picks)], (0, 1)
        pairs = ModelNetPairs(shapes, 512, kind, seed=1)
        picks = np.random.default_rng(3).choice(len(pairs), 100, replace=False)
        return "modelnet40", [(it["source"], it["target"], it["transform"]) for it in
                              (pairs[int(i)] for i in picks)], (0,)

    print("| pairs | PDSAC (hypotheses x sample size, local candidates) | alone: RE mean / median (deg), success "
          "| refined |\n|---|---|---|---|")
    for kind in args.kinds:
        default, items, seeds = pairs_of(kind)
        scene = kind.startswith(("kidnap", "gap"))
        for checkpoint, setting in ((c, s) for c in args.checkpoints or [default] for s in args.settings):
            m, k, local, *rest = setting.split("x")
            tightening = PDSACConfig().refit_tightening if not rest else (
                () if rest[0] == "-" else tuple(float(f) for f in rest[0].split(",")))
            cells = []
            pdsac = PDSACConfig(num_hypotheses=int(m), sample_size=int(k), local_candidates=int(local),
                                refit_tightening=tightening)
            refined = SCENE_REGISTRATION.refine if scene else RefineConfig(method="point_to_point")
            for refine in (RefineConfig(), refined):
                method = refine.method
                errors = []
                for seed in seeds:
                    cfg = RegistrationConfig(seed=seed, refine=refine, pdsac=pdsac)
                    registrar = Registrar.from_checkpoint(checkpoint, cfg, num_points=args.num_points)
                    errors += [transform_errors(registrar.register(s, t).transformation, T)
                               for s, t, T in tqdm(items, desc=f"{kind} {setting} {method}", leave=False)]
                e = np.array(errors)
                ok = (e[:, 0] < 2.0) & (e[:, 1] < 0.05) if scene else e[:, 0] < 5.0
                cells.append(f"{e[:, 0].mean():.2f} / {np.median(e[:, 0]):.2f}, {ok.mean():.1%}")
            print(f"| {kind}, `{checkpoint}` | {m} x {k}, {local}, tightening {tightening or '-'} | {cells[0]} "
                  f"| {cells[1]} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
