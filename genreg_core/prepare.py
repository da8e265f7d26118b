"""Pipeline stage "prepare": validate a pair, apply the initial guess, normalise, subsample.

The one place where a (source, target) pair becomes network input; the registration pipeline, the
benchmarks, the ablations and the scripts all call `prepare_pair`.

Frames and units: see `genreg_core.geometry`. Both clouds are subsampled, seeded, to the model's N
(network) and to the refinement size (ICP and fitness); the source subsets are moved by the initial guess
(identity if none). Both are then normalised by one similarity taken from the guess-moved source's robust
extent (`robust_extent`: x_n = (x - offset) / scale, so the source fills the unit box, as in training, and
a few stray points cannot shrink it). A transform estimated between the normalised clouds maps back with
`PreparedPair.to_input_units`; distance settings map into that frame with `model_frame_config`.

Cost: about one read of each input cloud. The finite check is one pass (a sum; a per-row mask only when
it is not finite), no float64 copy of a cloud is made (only the subsets are float64), the draws cost O(N)
whatever the cloud size (`sample_indices`), and the aligned full-resolution source is one float32 matrix
product (`transform_rows`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import open3d as o3d
import torch

from genreg_core import kernels
from genreg_core.config import (
    AUTO_GUARD_DISTANCE,
    AUTO_ICP_DISTANCE,
    AUTO_INLIER_THRESHOLD,
    RegistrationConfig,
)
from genreg_core.errors import InvalidPointCloudError, NonFinitePointsError, TooFewPointsError
from genreg_core.geometry import apply_transform, denormalize_transform
from genreg_core.refine import o3d_cloud
from genreg_core.score import TargetIndex, sorted_distinct

ROBUST_QUANTILE = 0.001  # robust_extent ignores this share of the points on each side of each axis
# No normalised point may lie farther than this many source extents from the source's box: beyond it the
# network's squared distances leave float32 (and no registration is meaningful: clouds in other units)
MAX_REACH = 1e6
MIN_SPREAD = 1e-6  # ... and no normalised cloud may span less than this many source extents (it is a point)


def validate_cloud(points: object, name: str, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Check an (N, 3) real array; return (its finite rows, finite-row mask).

    The finite rows keep the input's dtype (float32, float64 or integer) and are the input array itself
    (no copy) when every row is finite: one pass over the data finds that out. Raises
    InvalidPointCloudError (shape/dtype), NonFinitePointsError (no finite point) or TooFewPointsError
    (fewer than `min_points` finite points).
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
    mask = finite_rows(points)
    count = len(points) if mask is None else int(np.count_nonzero(mask))
    if count == 0:
        raise NonFinitePointsError(f"{name} has no finite points ({len(points)} given, all NaN/Inf or empty)")
    if count < min_points:
        raise TooFewPointsError(f"{name} has {count} finite points; registration needs at least {min_points}")
    if mask is None:
        return points, np.ones(len(points), dtype=bool)
    return np.compress(mask, points, axis=0), mask


def finite_rows(points: np.ndarray) -> np.ndarray | None:
    """Which rows of an (N, 3) array are finite; None if all are (the common case: one pass, no mask)."""
    if points.dtype.kind != "f":
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(points.sum()):  # a finite sum: no NaN or Inf anywhere
            return None
    finite = np.isfinite(points)  # a NaN or Inf somewhere, or an overflowing sum of huge values
    mask = finite[:, 0] & finite[:, 1]  # column by column: all(axis=1) over 3 columns is 10x slower
    mask &= finite[:, 2]
    return None if mask.all() else mask


def check_transform(T: object, name: str = "initial_guess") -> np.ndarray:
    """A finite 4x4 proper rigid transform as float64, else InvalidPointCloudError."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidPointCloudError(f"{name} must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InvalidPointCloudError(f"{name} must be a proper rigid transform (orthonormal R, det +1)")
    return T


def sample_indices(count: int, n: int, rng: np.random.Generator, ordered: bool = False) -> np.ndarray:
    """n random row indices of range(count), seeded by `rng`: a uniform random subset without replacement
    if count >= n, in random order (`ordered`: ascending, for gathering rows in memory order); else every
    row once plus n - count repeats, shuffled.

    O(n) time and memory whatever `count` (no permutation of all rows): from a large cloud it draws a few
    more than n with replacement, keeps the distinct ones (drawing again in the rare case that too few
    were distinct: a uniform random subset of their number) and drops the surplus at random; a
    permutation of all rows only when count < 4 n.
    """
    if count < n:
        extra = rng.integers(0, count, n - count)
        return rng.permutation(np.concatenate([np.arange(count), extra]))
    if count < 4 * n:
        picked = rng.permutation(count)[:n]
        return np.sort(picked) if ordered else picked
    distinct = np.empty(0, dtype=np.int64)
    while len(distinct) < n:
        draws = rng.integers(0, count, n - len(distinct) + n * n // count + 8)  # + the expected repeats
        distinct = sorted_distinct(np.concatenate([distinct, draws]))
    picked = np.delete(distinct, rng.choice(len(distinct), len(distinct) - n, replace=False))
    return picked if ordered else rng.permutation(picked)


def subsample(points: np.ndarray, n: int, rng: np.random.Generator, ordered: bool = False) -> np.ndarray:
    """n random rows (`sample_indices`) as float64: without replacement if there are enough, else all
    rows plus repeats; `ordered`: in input order."""
    return points[sample_indices(len(points), n, rng, ordered)].astype(np.float64)


# Row hashing of `repeated_rows`: three odd 64-bit multipliers (a multiplicative hash of each coordinate's bits)
_ROW_HASH = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9], dtype=np.uint64)


def repeated_rows(points: np.ndarray) -> np.ndarray:
    """Which rows of a float64 (n, 3) array repeat an earlier-sorted row exactly (-0.0 equals 0.0): one
    sort of a 64-bit hash per row, the rows compared where the hashes agree. No two hashes alike (the common
    case) is told by sorting the hashes alone, several times faster than the stable argsort that orders the rows."""
    x = np.ascontiguousarray(points, dtype=np.float64) + 0.0  # + 0.0: -0.0 becomes 0.0
    with np.errstate(over="ignore"):
        key = (x.view(np.uint64) * _ROW_HASH).sum(axis=1, dtype=np.uint64)  # wraps: a hash
    repeated = np.zeros(len(x), dtype=bool)
    ordered = np.sort(key)
    if not (ordered[1:] == ordered[:-1]).any():
        return repeated
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    later, earlier = order[1:][same], order[:-1][same]
    repeated[later[(x[later] == x[earlier]).all(axis=1)]] = True
    return repeated


def distinct_points(points: np.ndarray) -> np.ndarray:
    """The distinct rows of an (N, 3) array as float64, in input order."""
    rows = points.astype(np.float64)
    return rows[~repeated_rows(rows)]


def distinct_subsample(points: np.ndarray, n: int, rng: np.random.Generator, ordered: bool = False,
                       repeat: bool = True, rounds: int = 4) -> np.ndarray:
    """`subsample` without repeated points: drawn rows that repeat another drawn point (a LiDAR's dual
    returns, a float32 cloud quantised far from the origin) are replaced by fresh draws, for a few rounds;
    a cloud with too few distinct points for that is subsampled from its distinct points, with repeats
    only if it has fewer than n (none if not `repeat`: then all of them once). Identical to `subsample`
    when no drawn point repeats another. Repeated points would give the network zero-length edges and
    spread-free neighbourhoods, and the scores a zero spacing."""
    if len(points) <= n and not repeat:
        return distinct_points(points)
    rows = subsample(points, n, rng, ordered)
    if len(points) < n:  # every row once plus repeats: repeats of distinct points are as `subsample`
        distinct = distinct_points(points)
        return rows if len(distinct) == len(points) else subsample(distinct, n, rng, ordered)
    repeated = repeated_rows(rows)
    for _ in range(rounds):
        if not repeated.any():
            return rows
        fresh = points[rng.integers(0, len(points), int(repeated.sum()))].astype(np.float64)
        rows = np.concatenate([rows[~repeated], fresh])
        repeated = repeated_rows(rows)
    if not repeated.any():
        return rows
    distinct = distinct_points(points)
    return distinct if len(distinct) <= n and not repeat else subsample(distinct, n, rng, ordered)


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
    with np.errstate(over="ignore"):  # an overflowing extent is refused by the caller
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
    float32; `dense_src`, `dense_tgt`: the refinement-size clouds, normalised, float32 (`dense_tgt`
    read-only); `src`, `src_mask`: the finite input source rows (the input array itself, in its dtype,
    when all rows are finite: read, never written) and which rows they were; `init`: the initial guess
    (None if none was given); the similarity `offset`, `scale`."""

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

    def aligned_source(self, T: np.ndarray) -> np.ndarray:
        """The finite input source rows moved by the input-units transform T, float32, input order."""
        return transform_rows(T, self.src)

    @cached_property
    def target_index(self) -> TargetIndex:
        """The nearest-neighbour index of `dense_tgt` the scores share (built on first use, once per pair)."""
        return TargetIndex(self.dense_tgt)

    @cached_property
    def plane_target(self) -> o3d.geometry.PointCloud:
        """`dense_tgt` as an Open3D cloud carrying `target_index`'s normals (the PCA of `score.NORMAL_NEIGHBOURS`
        neighbours, as Open3D's KNN normals): point-to-plane ICP's target. Its normals are computed once per
        pair and shared by every ICP of the pair (refinement, guess, guard) and by the covariance."""
        cloud = o3d_cloud(self.dense_tgt)
        cloud.normals = o3d.utility.Vector3dVector(self.target_index.normals(np.arange(len(self.dense_tgt))))
        return cloud


def transform_rows(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """x' = R x + t for the rows of an (N, 3) array, as float32, at about memory speed: one compiled pass
    (`kernels.transform_rows`) in float32 for float32 input (float32 R and t), in float64 for other dtypes
    (float64, integers), with no copy of the input."""
    dtype = np.float32 if points.dtype == np.float32 else np.float64
    return kernels.transform_rows(np.ascontiguousarray(T, dtype=dtype), points)


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

    def subset(points: np.ndarray, n: int, dense: bool = False) -> np.ndarray:
        """n rows as float64, distinct points where there are enough (`distinct_subsample`). `dense` (the
        ICP and fitness sets, whose order is immaterial): every distinct point if there are few enough
        (never a repeat), else the draw in input order (gathered in memory order)."""
        return distinct_subsample(points, n, rng, ordered=dense, repeat=not dense)

    a, b = subset(src, num_points), subset(tgt, num_points)
    dense_src, dense_tgt = subset(src, refine_points, dense=True), subset(tgt, refine_points, dense=True)
    for name, dense in (("source", dense_src), ("target", dense_tgt)):
        if len(dense) < min_points:
            raise TooFewPointsError(f"{name} has {len(dense)} distinct finite points; registration needs at least "
                                    f"{min_points}")
    if init is not None:
        a, dense_src = apply_transform(init, a), apply_transform(init, dense_src)
    offset, scale = robust_extent(dense_src)  # one similarity for both clouds
    if not np.isfinite(scale):
        raise InvalidPointCloudError(f"source extent overflows float64 ({scale}): coordinates too large")

    def normalized(points: np.ndarray, name: str) -> np.ndarray:
        with np.errstate(over="ignore"):  # finite input: an overflow is inf, never NaN
            moved = ((points - offset) / scale).astype(np.float32)
        reach = float(np.abs(moved).max())
        if reach > MAX_REACH:
            raise InvalidPointCloudError(f"a cloud reaches {reach:.3g} source extents (of {scale:.3g}) from the source, "
                                         f"more than {MAX_REACH:.0e}: are both clouds in the same units?")
        spread = float(np.ptp(moved, axis=0).max())
        if spread < MIN_SPREAD:  # a point at the source's scale (squared distances in it leave float32)
            raise InvalidPointCloudError(f"the {name} spans {spread:.3g} source extents (of {scale:.3g}), less than "
                                         f"{MIN_SPREAD:.0e}: are both clouds in the same units?")
        return moved

    target = normalized(dense_tgt, "target")
    target.setflags(write=False)  # immutable: `target_index` indexes it once for the pair
    return PreparedPair(src, src_mask, init, offset, scale, normalized(a, "source"), normalized(b, "target"),
                        normalized(dense_src, "source"), target, time.perf_counter() - t0)
