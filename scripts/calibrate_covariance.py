"""Calibrate the covariance model (`score.COVARIANCE_INFLATION`, `COVARIANCE_FLOOR_M`, `_RAD`) on training
pairs and check it on held-out pairs.

`RegistrationResult.covariance` (ROS order x, y, z, rotation about x, y, z) is calibrated when the
normalised squared error e' C^-1 e of the pose error e = (t_est - t_gt, rotvec(R_est R_gt^T)) has mean 6
(its dimension). The script registers real frame pairs with the scene model: on redkitchen training frames
(0-799) it records each pair's error and raw Gauss-Newton covariance (`score.pose_covariance` with
inflation 1 and no floor, on the registration's own refinement clouds: `Registrar.prepare` with the same
seed), sets the floor to the median
per-axis error (translation, rotation) of those pairs and then the inflation that makes the mean 6 there.
It then prints the mean with those constants on redkitchen validation frames (800-999) and on SUN3D
(never trained on). Same gaps everywhere. Settings: the scene preset `config.SCENE_REGISTRATION` (the
node's scene settings); --method swaps its refinement method.

    python scripts/calibrate_covariance.py --pairs 40
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from genreg_core.config import SCENE_REGISTRATION
from genreg_core.data import RGBDSequence
from genreg_core.geometry import apply_transform
from genreg_core.registration import Registrar
from genreg_core.score import fitness_distance, pose_covariance

GAPS = (1, 5, 10)


def pose_error(T: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """e = (t - t_gt, rotvec(R R_gt^T)): the covariance's perturbation (parent frame)."""
    return np.concatenate([T[:3, 3] - T_gt[:3, 3], Rotation.from_matrix(T[:3, :3] @ T_gt[:3, :3].T).as_rotvec()])


def raw_covariance(reg: Registrar, source: np.ndarray, target: np.ndarray, T: np.ndarray) -> np.ndarray | None:
    """The Gauss-Newton covariance of the pose T (target_from_source) without inflation or floor, computed as
    the registration computes it: on the pair's refinement clouds in its normalised frame, metric output."""
    p = reg.prepare(source, target)  # the config's seed: the same clouds as `reg.register`
    moved = apply_transform(p.to_normalized(T), p.dense_src.astype(np.float64))
    origin = (T[:3, 3] - p.offset) / p.scale  # the pose's position, normalised frame
    return pose_covariance(moved, p.target_index, origin, fitness_distance(p.target_index), inflation=1.0,
                           floor=(0.0, 0.0), scale=p.scale)


def collect(reg: Registrar, seq: RGBDSequence, frames: range, count: int, rng: np.random.Generator,
            stride: int, label: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(error, Gauss-Newton covariance without floor or inflation) of `count` random pairs."""
    starts = [i for i in frames if all(i + g in seq for g in GAPS)]
    out = []
    for i in tqdm(rng.choice(starts, size=min(count, len(starts)), replace=False), desc=label, leave=False):
        j = int(i) + int(rng.choice(GAPS))
        source, target = seq.points(j, stride=stride), seq.points(int(i), stride=stride)
        T = reg.register(source, target).transformation
        covariance = raw_covariance(reg, source, target, T)
        if covariance is not None:
            out.append((pose_error(T, seq.relative_pose(j, int(i))), covariance))
    return out


def mean_nees(samples: list[tuple[np.ndarray, np.ndarray]], inflation: float, floor: tuple[float, float]) -> float:
    floor_cov = np.diag([floor[0] ** 2] * 3 + [floor[1] ** 2] * 3)
    return float(np.mean([e @ np.linalg.solve(inflation * C + floor_cov, e) for e, C in samples]))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--method", default=SCENE_REGISTRATION.refine.method,
                   help="refinement method (default: the scene preset's)")
    p.add_argument("--stride", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    scene = replace(SCENE_REGISTRATION, refine=replace(SCENE_REGISTRATION.refine, method=args.method))
    reg = Registrar.from_checkpoint("7scenes", scene)
    kitchen = RGBDSequence.redkitchen()
    train = collect(reg, kitchen, range(790), args.pairs, rng, args.stride, "train")
    errors = np.array([e for e, _ in train])
    floor = (float(np.median(np.linalg.norm(errors[:, :3], axis=1))) / np.sqrt(3),
             float(np.median(np.linalg.norm(errors[:, 3:], axis=1))) / np.sqrt(3))
    inflation = brentq(lambda k: mean_nees(train, k, floor) - 6.0, 1e-6, 1e6) if mean_nees(train, 1e-6, floor) > 6 else 0.0
    print(f"{args.method}, gaps {GAPS}, stride {args.stride}")
    print(f"training pairs (redkitchen 0-799, {len(train)}): mean NEES {mean_nees(train, 1.0, (0, 0)):.1f} uncalibrated; "
          f"floor {floor[0] * 100:.2f} cm, {np.degrees(floor[1]):.3f} deg; inflation {inflation:.2f}")
    for label, seq, frames in (("redkitchen validation 800-999", kitchen, range(800, 990)),
                               ("sun3d fragment 1", RGBDSequence.sun3d(1), range(935, 975)),
                               ("sun3d fragment 2", RGBDSequence.sun3d(2), range(3160, 3200))):
        held = collect(reg, seq, frames, args.pairs, rng, args.stride, label)
        print(f"{label} ({len(held)} pairs): mean NEES {mean_nees(held, inflation, floor):.1f} calibrated "
              f"(expected 6), {mean_nees(held, 1.0, (0, 0)):.1f} uncalibrated")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
