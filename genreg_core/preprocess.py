"""Cloud preprocessing before registration: range filter, crop box, voxel downsample (numpy, no ROS).

Conventions: points are rows of an (N, 3) array in the sensor's own frame and units (metres for
ROS data, REP-103); ranges are Euclidean distances from that frame's origin. Every step keeps only
finite points and returns a new array; the input is never modified (see `preprocess` for the no-op case).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from genreg_core.config import check_ranges, setting
from genreg_core.errors import ConfigError


@dataclass(frozen=True)
class PreprocessConfig:
    """Which filters run, in this order: range, crop box, voxel grid. Zero / None switches one off."""

    min_range: float = setting(0.0, "Drop points closer than this to the sensor origin, m (0: off).",
                               low=0.0, high=1e4)
    max_range: float = setting(0.0, "Drop points farther than this from the sensor origin, m (0: off).",
                               low=0.0, high=1e4)
    crop_min: tuple[float, ...] | None = setting(None, "Crop box minimum corner [x, y, z] in the cloud's "
                                                 "frame, m (none: off; both corners or neither).")
    crop_max: tuple[float, ...] | None = setting(None, "Crop box maximum corner [x, y, z], m (none: off).")
    voxel_size: float = setting(0.0, "Voxel-grid downsampling edge, m; one centroid per voxel (0: off).",
                                low=0.0, high=100.0)

    def __post_init__(self) -> None:
        check_ranges(self, "preprocess.")
        if self.max_range and self.min_range >= self.max_range:
            raise ConfigError(f"min_range {self.min_range} must be < max_range {self.max_range}")
        if (self.crop_min is None) != (self.crop_max is None):
            raise ConfigError("crop_min and crop_max must be given together")
        if self.crop_min is not None:
            lo, hi = np.asarray(self.crop_min, float), np.asarray(self.crop_max, float)
            if lo.shape != (3,) or hi.shape != (3,) or not (lo < hi).all():
                raise ConfigError(f"crop box needs 3 values each with min < max, got {self.crop_min}, {self.crop_max}")


def range_mask(points: np.ndarray, min_range: float = 0.0, max_range: float = 0.0) -> np.ndarray:
    """(N,) bool: finite points with min_range <= |p| <= max_range (a zero bound is open)."""
    sq = np.einsum("ij,ij->i", points, points)
    keep = np.isfinite(sq)
    if min_range > 0:
        keep &= sq >= min_range**2
    if max_range > 0:
        keep &= sq <= max_range**2
    return keep


def crop_mask(points: np.ndarray, crop_min: np.ndarray, crop_max: np.ndarray) -> np.ndarray:
    """(N,) bool: points inside the closed axis-aligned box [crop_min, crop_max]."""
    lo, hi = np.asarray(crop_min), np.asarray(crop_max)
    return ((points >= lo) & (points <= hi)).all(axis=1)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroid of the points in each occupied cubic voxel of edge `voxel_size` (grid anchored at 0).

    Output order follows the voxels' first appearance in the input, so it is deterministic. Finite float32 or
    float64 points are voxelised by the compiled `kernels.voxel_centroids` (one pass, a hash table of the
    voxels), others by `voxel_downsample_reference` (sorts), which gives the same centroids bit for bit.
    """
    if voxel_size <= 0 or len(points) == 0:
        return points.copy()
    if points.dtype in (np.float32, np.float64) and np.isfinite(points).all():
        from genreg_core import kernels  # numba and torch: not for the settings' importers of this module

        return kernels.voxel_centroids(np.ascontiguousarray(points), np.array([voxel_size], dtype=points.dtype))
    return voxel_downsample_reference(points, voxel_size)


def voxel_downsample_reference(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """`voxel_downsample` by sorting the voxels' keys (numpy): the form for points the compiled kernel does not
    take (other dtypes, non-finite rows) and the reference it is tested against."""
    if voxel_size <= 0 or len(points) == 0:
        return points.copy()
    scaled = points / voxel_size
    keys = np.floor(scaled, out=scaled).astype(np.int64)  # in place: a map's temporaries cost page faults
    del scaled
    # per column: numpy's axis-0 reductions of an (N, 3) array are ten times slower
    low = np.array([keys[:, i].min() for i in range(3)])
    keys -= low
    dims = np.array([keys[:, i].max() for i in range(3)]) + 1
    if float(np.prod(dims.astype(np.float64))) < 2**62:  # one int64 key per voxel: a 1D sort
        flat = keys[:, 0] * dims[1]
        flat += keys[:, 1]
        flat *= dims[2]
        flat += keys[:, 2]
        # np.unique(flat, return_inverse=True) by one stable sort (timsort for int64: 2-3x faster than
        # np.unique's sort on LiDAR scans and maps, whose keys come in runs); a voxel's first point in the
        # stable order is its first in the input
        order = np.argsort(flat, kind="stable")
        ordered = flat[order]
        starts = np.empty(len(ordered), dtype=bool)
        starts[0] = True
        np.not_equal(ordered[1:], ordered[:-1], out=starts[1:])
        inverse = np.empty(len(points), dtype=np.int64)
        inverse[order] = np.cumsum(starts) - 1
        first = order[starts]
    else:  # a huge grid (tiny voxels over a huge span): sort the rows
        voxels, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        # each voxel's first point (np.unique's return_index sorts stably: five times slower on LiDAR scans)
        first = np.full(len(voxels), len(points), dtype=np.int64)
        np.minimum.at(first, inverse, np.arange(len(points), dtype=np.int64))
    counts = np.bincount(inverse)
    sums = np.stack([np.bincount(inverse, weights=points[:, i]) for i in range(3)], axis=1)
    centroids = (sums / counts[:, None]).astype(points.dtype)
    return centroids[np.argsort(first, kind="stable")]


def preprocess(points: np.ndarray, config: PreprocessConfig) -> np.ndarray:
    """Apply the configured filters; returns the kept (and possibly downsampled) finite points.

    With every filter off the input array itself is returned (no copy, non-finite points kept).
    """
    pts = np.asarray(points)
    if not (config.min_range or config.max_range or config.crop_min is not None or config.voxel_size):
        return pts
    keep = range_mask(pts, config.min_range, config.max_range)
    if config.crop_min is not None:
        keep &= crop_mask(pts, config.crop_min, config.crop_max)
    pts = np.compress(keep, pts, axis=0)  # 5x faster than pts[keep] on (N, 3) rows
    return voxel_downsample(pts, config.voxel_size) if config.voxel_size > 0 else pts
