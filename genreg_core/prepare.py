"""Pipeline stage "prepare": validate a pair, apply the initial guess, normalise, subsample.

The one place where a (source, target) pair becomes network input; the registration pipeline, the
benchmarks, the ablations and the scripts all call `prepare_pair`.

Frames and units: see `genreg_core.geometry`. Both clouds are subsampled, seeded, to the model's N
(network) and to the refinement size (ICP and fitness); the source subsets are moved by the initial guess
(identity if none). Both are then normalised by one similarity taken from the guess-moved source's robust
extent (`robust_extent`: x_n = (x - offset) / scale, so the source fills the unit box, as in training, and
a few stray points cannot shrink it). A transform estimated between the normalised clouds maps back with
`PreparedPair.to_input_units`; distance settings map into that frame with `model_frame_config`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from genreg_core.config import (
    AUTO_GUARD_DISTANCE,
    AUTO_ICP_DISTANCE,
    AUTO_INLIER_THRESHOLD,
    RegistrationConfig,
)
from genreg_core.errors import InvalidPointCloudError, NonFinitePointsError, TooFewPointsError
from genreg_core.geometry import apply_transform, denormalize_transform

ROBUST_QUANTILE = 0.001  # robust_extent ignores this share of the points on each side of each axis


def validate_cloud(points: object, name: str, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Check an (N, 3) real array; return (finite points as float64, finite-row mask).

    Raises InvalidPointCloudError (shape/dtype), NonFinitePointsError (no finite point) or
    TooFewPointsError (fewer than `min_points` finite points).
    """
    if not isinstance(points, np.ndarray):
        if isinstance(points, torch.Tensor):
            points = points.detach().cpu().numpy()
        else:
            raise InvalidPointCloudError(f"{name} must be a numpy array of shape (N, 3), got {type(points).__name__}")
    if points.dtype.kind not in "fiu" or points.dtype == np.float16:
        raise InvalidPointCloudError(f"{name} must hold float32/float64 (or integer) values, got dtype {points.dtype}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidPointCloudError(f"{name} must have shape (N, 3), got {points.shape}")
    mask = np.isfinite(points).all(axis=1)
    count = int(mask.sum())
    if count == 0:
        raise NonFinitePointsError(f"{name} has no finite points ({len(points)} given, all NaN/Inf or empty)")
    if count < min_points:
        raise TooFewPointsError(f"{name} has {count} finite points; registration needs at least {min_points}")
    return points[mask].astype(np.float64, copy=False), mask


def check_transform(T: object, name: str = "initial_guess") -> np.ndarray:
    """A finite 4x4 proper rigid transform as float64, else InvalidPointCloudError."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidPointCloudError(f"{name} must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InvalidPointCloudError(f"{name} must be a proper rigid transform (orthonormal R, det +1)")
    return T


def subsample(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random points: without replacement if there are enough, else all points plus repeats."""
    if len(points) >= n:
        return points[rng.choice(len(points), n, replace=False)]
    extra = rng.choice(len(points), n - len(points), replace=True)
    return points[rng.permutation(np.concatenate([np.arange(len(points)), extra]))]


def robust_extent(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(lower corner, edge) of the cube the points fill, ignoring the floor(`ROBUST_QUANTILE` n) outermost
    points on each side of each axis (none below 1000 points: the bounding box): the normalisation offset
    and scale, robust to a few stray points."""
    k = int(ROBUST_QUANTILE * len(points))
    if k == 0:
        lo, hi = points.min(axis=0), points.max(axis=0)
    else:
        ordered = np.partition(points, [k, len(points) - 1 - k], axis=0)
        lo, hi = ordered[k], ordered[len(points) - 1 - k]
    return lo, float(max((hi - lo).max(), 1e-12))


def model_frame_config(cfg: RegistrationConfig, scale: float) -> RegistrationConfig:
    """`cfg` with its distances in the normalised frame of a pair of this `scale`: metres / scale, or the
    auto fraction of the robust extent where the setting is 0."""
    def frame(value: float, auto: float) -> float:
        return value / scale if value > 0 else auto

    r = cfg.refine
    return replace(
        cfg,
        pdsac=replace(cfg.pdsac, inlier_threshold=frame(cfg.pdsac.inlier_threshold, AUTO_INLIER_THRESHOLD)),
        refine=replace(r, max_correspondence_distance=frame(r.max_correspondence_distance, AUTO_ICP_DISTANCE),
                       guard_distance=frame(r.guard_distance, AUTO_GUARD_DISTANCE)),
    )


@dataclass(frozen=True)
class PreparedPair:
    """One pair ready for the network. `a`, `b`: the model-N source (guess-moved) and target, normalised,
    float32; `dense_src`, `dense_tgt`: the refinement-size clouds, normalised; `src`, `src_mask`: the finite
    input source rows and which rows they were; `init`: the initial guess (None if none was given); the
    similarity `offset`, `scale`."""

    src: np.ndarray
    src_mask: np.ndarray
    init: np.ndarray | None
    offset: np.ndarray
    scale: float
    a: np.ndarray
    b: np.ndarray
    dense_src: np.ndarray
    dense_tgt: np.ndarray
    seconds: float

    def to_input_units(self, T_n: np.ndarray) -> np.ndarray:
        """A normalised-frame estimate (b ~ T_n a) as the input's target_from_source."""
        return denormalize_transform(T_n, self.offset, self.scale) @ self.guess

    @property
    def guess(self) -> np.ndarray:
        """The initial guess, identity if none was given."""
        return np.eye(4) if self.init is None else self.init

    def to_normalized(self, T: np.ndarray) -> np.ndarray:
        """An input-units target_from_source in this pair's normalised frame (inverse of `to_input_units`):
        S T init^-1 S^-1 with the similarity S x = (x - offset) / scale."""
        S = np.diag([1.0 / self.scale] * 3 + [1.0])
        S[:3, 3] = -np.asarray(self.offset) / self.scale
        return S @ T @ np.linalg.inv(self.guess) @ np.linalg.inv(S)

    def points_to_input_units(self, points_n: np.ndarray) -> np.ndarray:
        """Normalised points back to input units (the similarity only; no guess)."""
        return points_n * self.scale + self.offset


def prepare_pair(
    source: object,
    target: object,
    initial_guess: object | None = None,
    *,
    num_points: int,
    refine_points: int,
    min_points: int = 32,
    seed: int | None = 0,
) -> PreparedPair:
    """Validate, guess-move, normalise and subsample one pair (module docstring). Bad input raises a
    named `genreg_core.errors` exception."""
    t0 = time.perf_counter()
    src, src_mask = validate_cloud(source, "source", min_points)
    tgt, _ = validate_cloud(target, "target", min_points)
    init = None if initial_guess is None else check_transform(initial_guess)
    rng = np.random.default_rng(seed)

    def subset(points: np.ndarray, n: int, keep_all: bool = False) -> np.ndarray:
        return points if keep_all and len(points) <= n else subsample(points, n, rng)

    a, b = subset(src, num_points), subset(tgt, num_points)
    dense_src, dense_tgt = subset(src, refine_points, keep_all=True), subset(tgt, refine_points, keep_all=True)
    if init is not None:
        a, dense_src = apply_transform(init, a), apply_transform(init, dense_src)
    offset, scale = robust_extent(dense_src)  # one similarity for both clouds

    def normalized(points: np.ndarray) -> np.ndarray:
        return ((points - offset) / scale).astype(np.float32)

    return PreparedPair(src, src_mask, init, offset, scale, normalized(a), normalized(b), normalized(dense_src),
                        normalized(dense_tgt), time.perf_counter() - t0)
