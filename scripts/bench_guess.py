"""Does an initial guess help, and can a noisy one hurt? Real frame pairs, the scene model.

For each pair (redkitchen validation frames 800-999 and SUN3D, never trained on) the pipeline runs with
no guess, with a noisy guess (the ground truth moved by 2 deg about a random axis and 5 cm in a random
direction) and with the exact ground truth, for each refinement method (--methods): it compares refinements,
so each runs from the scene preset `config.SCENE_REGISTRATION` (scene PDSAC) with that method at the API's
default refinement settings, not the preset's GICP with 20 iterations. Prints RE / TE mean and median,
success (RE < 2 deg and TE < 5 cm) and how many pairs the noisy guess made worse than no guess (by more
than 0.5 deg or 2 cm).

    python scripts/bench_guess.py --pairs 20 --threads 2
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from genreg_core.config import SCENE_REGISTRATION, RefineConfig
from genreg_core.data import RGBDSequence
from genreg_core.geometry import make_transform
from genreg_core.metrics import transform_errors
from genreg_core.registration import Registrar


def noisy(T: np.ndarray, rng: np.random.Generator, deg: float = 2.0, metres: float = 0.05) -> np.ndarray:
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis, direction = axis / np.linalg.norm(axis), direction / np.linalg.norm(direction)
    return make_transform(Rotation.from_rotvec(np.radians(deg) * axis).as_matrix(), metres * direction) @ T


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=20, help="pairs per dataset")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--stride", type=int, default=2)
    p.add_argument("--methods", nargs="+", default=["none", "point_to_plane"])
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    datasets = {"redkitchen-gap10": (RGBDSequence.redkitchen(), range(800, 990), 10),
                "sun3d-gap5": (RGBDSequence.sun3d(1), range(935, 980), 5),
                "sun3d2-gap5": (RGBDSequence.sun3d(2), range(3160, 3205), 5)}
    print(f"{args.threads} threads, stride {args.stride}, {args.pairs} pairs per dataset; success: RE < 2 deg, TE < 5 cm")
    print("| dataset | refine | guess | RE mean / median (deg) | TE mean / median (cm) | success | noisy worse than none |")
    print("|---|---|---|---|---|---|---|")
    for name, (seq, frames, gap) in datasets.items():
        starts = [i for i in frames if i + gap in seq]
        chosen = [int(i) for i in rng.choice(starts, size=min(args.pairs, len(starts)), replace=False)]
        pairs = [(seq.points(i + gap, stride=args.stride), seq.points(i, stride=args.stride), seq.relative_pose(i + gap, i))
                 for i in chosen]
        guesses = [noisy(T, rng) for *_, T in pairs]
        for method in args.methods:
            reg = Registrar.from_checkpoint("7scenes", replace(SCENE_REGISTRATION, refine=RefineConfig(method=method)))
            errors = {}
            for label in ("none", "noisy", "exact"):
                errors[label] = np.array([
                    transform_errors(reg.register(s, t, {"none": None, "noisy": g, "exact": T}[label]).transformation, T)
                    for (s, t, T), g in tqdm(list(zip(pairs, guesses, strict=True)), desc=f"{name} {method} {label}",
                                             leave=False)])
            worse = int(np.sum((errors["noisy"][:, 0] > errors["none"][:, 0] + 0.5)
                               | (errors["noisy"][:, 1] > errors["none"][:, 1] + 0.02)))
            for label, e in errors.items():
                ok = np.mean((e[:, 0] < 2.0) & (e[:, 1] < 0.05))
                print(f"| {name} | {method} | {label} | {e[:, 0].mean():.2f} / {np.median(e[:, 0]):.2f} | "
                      f"{100 * e[:, 1].mean():.1f} / {100 * np.median(e[:, 1]):.1f} | {ok:.0%} | "
                      f"{worse if label == 'noisy' else ''} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
