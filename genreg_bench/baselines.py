"""Classical registration baselines (Open3D, small_gicp, KISS-Matcher), configured as a skilled user would.

ICP, downsampling and normals are the core's (`genreg_core.refine.icp`, the one ICP wrapper), FPFH and
RANSAC the core's fallback (`genreg_core.fallback`); FGR, small_gicp and KISS-Matcher (pip
`kiss-matcher`, imported on first use) live here.

Every method is a plain function `(source, target, params) -> (T, seconds)`:
- source (N, 3) and target (M, 3) arrays in any units (unit box for objects, metres for scenes);
- T is the 4x4 float64 target_from_source transform, column convention x_t = R x_s + t;
- seconds is the wall time of the whole method, preprocessing (downsampling, normals, FPFH) included.
All lengths live in `BaselineParams` in the clouds' units: `BaselineParams.unit_box()` for clouds in the
unit box [0, 1]^3, `BaselineParams.unit_sphere()` for shapes at ModelNet40's stored unit-sphere scale
(the unit-box settings doubled) and `BaselineParams.metric_scene()` for RGB-D frames in metres;
`scaled(extent)` turns the unit-box settings into an equivalent for a cloud whose bounding box is
`extent` wide. `fpfh+ransac+icp` on scenes is the fast setting (5 cm voxels); `fpfh+ransac+icp-accurate`
halves the feature voxel, normal and FPFH radii and the RANSAC distance (`accurate()`: 2.5 cm voxels).
Threads: Open3D follows OMP_NUM_THREADS (set it before import); small_gicp takes `params.threads`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import small_gicp

from genreg_core import fallback
from genreg_core.fallback import fpfh
from genreg_core.refine import gicp, icp

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class BaselineParams:
    """Every length is in the clouds' units (unit-box units or metres)."""

    icp_max_distance: float = 0.5  # ICP from identity (p2p, p2plane): correspondence cut-off
    icp_max_iterations: int = 50
    icp_voxel_size: float = 0.0  # ICP/GICP input downsampling voxel (0: the points as given)
    feature_voxel_size: float = 0.0  # FPFH pipelines: downsampling voxel (0: the points as given)
    normal_radius: float = 0.1  # normals for FPFH and point-to-plane (max 30 neighbours)
    fpfh_radius: float = 0.25  # FPFH support (max 100 neighbours)
    ransac_distance: float = 0.05  # RANSAC inlier distance (also its distance checker)
    ransac_max_iterations: int = 100_000
    ransac_confidence: float = 0.999
    fgr_distance: float = 0.05  # FGR correspondence distance (absolute scale, annealed)
    refine_distance: float = 0.1  # ICP after RANSAC: correspondence cut-off
    gicp_max_distance: float = 0.5  # small_gicp correspondence cut-off
    gicp_voxel_size: float = 0.005  # small_gicp downsampling (needs > 0)
    kiss_voxel_size: float = 0.025  # KISS-Matcher's voxel (its normal / FPFH radii: 3x / 5x of it)
    threads: int = 2  # small_gicp worker threads
    seed: int = 0  # Open3D RANSAC seed (multi-threaded RANSAC is still not bit-reproducible)

    @classmethod
    def unit_box(cls, threads: int = 2) -> BaselineParams:
        """Objects in the unit box [0, 1]^3 (ModelNet40, FMR-style pairs), 512-2048 points: no downsampling."""
        return cls(threads=threads)

    @classmethod
    def unit_sphere(cls, threads: int = 2) -> BaselineParams:
        """Shapes at ModelNet40's stored scale (unit sphere, 2 wide), ~540 points: the unit-box settings x2.
        KISS-Matcher's voxel is then 0.05: on 538-point RPM-Net crops of train shapes no voxel in 0.02-0.12
        (nor larger normal/FPFH gains) got it under 5 deg on more than 1 of 20 pairs; it is built for scans."""
        return cls.unit_box(threads).scaled(2.0)

    @classmethod
    def metric_scene(cls, threads: int = 2) -> BaselineParams:
        """RGB-D frames in metres (~300k points, 1-7 m deep), motions of centimetres between frames.
        KISS-Matcher at 5 cm voxels (the usual indoor RGB-D resolution, as 3DMatch's)."""
        return cls(
            icp_max_distance=0.1, icp_voxel_size=0.02, feature_voxel_size=0.05, normal_radius=0.1,
            fpfh_radius=0.25, ransac_distance=0.075, fgr_distance=0.05, refine_distance=0.05,
            gicp_max_distance=0.1, gicp_voxel_size=0.02, kiss_voxel_size=0.05, threads=threads,
        )

    def accurate(self) -> BaselineParams:
        """The feature pipeline at half the voxel: feature voxel, normal and FPFH radii, RANSAC distance."""
        return dataclasses.replace(self, feature_voxel_size=self.feature_voxel_size / 2,
                                   normal_radius=self.normal_radius / 2, fpfh_radius=self.fpfh_radius / 2,
                                   ransac_distance=self.ransac_distance / 2)

    def scaled(self, extent: float) -> BaselineParams:
        """These settings with every length multiplied by `extent` (the unit box is 1 wide)."""
        lengths = [f.name for f in dataclasses.fields(self) if f.type in ("float", float) and
                   ("distance" in f.name or "radius" in f.name or "voxel" in f.name)]
        return dataclasses.replace(self, **{k: getattr(self, k) * extent for k in lengths})


BaselineFn = Callable[[np.ndarray, np.ndarray, BaselineParams], tuple[np.ndarray, float]]


def ransac(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> np.ndarray:
    """FPFH + Open3D feature RANSAC (`genreg_core.fallback.fpfh_ransac`) with these settings."""
    return fallback.fpfh_ransac(source, target, voxel_size=p.feature_voxel_size, normal_radius=p.normal_radius,
                       fpfh_radius=p.fpfh_radius, distance=p.ransac_distance, max_iterations=p.ransac_max_iterations,
                       confidence=p.ransac_confidence, seed=p.seed)


def icp_point_to_point(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """Open3D point-to-point ICP from identity, cut-off `icp_max_distance`."""
    t0 = time.perf_counter()
    T = icp(source, target, method="point_to_point", max_distance=p.icp_max_distance,
            max_iterations=p.icp_max_iterations, voxel_size=p.icp_voxel_size)
    return T, time.perf_counter() - t0


def icp_point_to_plane(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """Open3D point-to-plane ICP from identity; target normals from a radius search (normal_radius)."""
    t0 = time.perf_counter()
    T = icp(source, target, method="point_to_plane", max_distance=p.icp_max_distance,
            max_iterations=p.icp_max_iterations, voxel_size=p.icp_voxel_size, normal_radius=p.normal_radius)
    return T, time.perf_counter() - t0


def fpfh_fgr(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """FPFH features on voxel-downsampled clouds, then Open3D Fast Global Registration (absolute scale)."""
    t0 = time.perf_counter()
    src, src_f = fpfh(source, p.feature_voxel_size, p.normal_radius, p.fpfh_radius)
    tgt, tgt_f = fpfh(target, p.feature_voxel_size, p.normal_radius, p.fpfh_radius)
    option = reg.FastGlobalRegistrationOption(
        use_absolute_scale=True, decrease_mu=True, maximum_correspondence_distance=p.fgr_distance
    )
    result = reg.registration_fgr_based_on_feature_matching(src, tgt, src_f, tgt_f, option)
    return np.asarray(result.transformation).copy(), time.perf_counter() - t0


def fpfh_ransac(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """FPFH + Open3D RANSAC (mutual filter, 3-point samples, edge-length and distance checkers)."""
    t0 = time.perf_counter()
    T = ransac(source, target, p)
    return T, time.perf_counter() - t0


def fpfh_ransac_icp(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """FPFH + RANSAC, then point-to-point ICP on the ICP-resolution clouds (cut-off `refine_distance`)."""
    t0 = time.perf_counter()
    T = icp(source, target, ransac(source, target, p), method="point_to_point", max_distance=p.refine_distance,
            max_iterations=p.icp_max_iterations, voxel_size=p.icp_voxel_size)
    return T, time.perf_counter() - t0


def fpfh_ransac_icp_accurate(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """`fpfh_ransac_icp` with `p.accurate()` (scenes: 2.5 cm feature voxels, 5 cm normals, 12.5 cm FPFH)."""
    return fpfh_ransac_icp(source, target, p.accurate())


def kiss_matcher_p2plane(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """KISS-Matcher (its own voxelisation at `kiss_voxel_size`, faster-PFH, ROBIN pruning, GNC solver; default
    gains), then Open3D point-to-plane ICP on the ICP-resolution clouds (cut-off `refine_distance`)."""
    import kiss_matcher

    t0 = time.perf_counter()
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel_size=p.kiss_voxel_size))
    solution = matcher.estimate(np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64))
    T = np.eye(4)
    T[:3, :3] = np.asarray(solution.rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(solution.translation, dtype=np.float64).reshape(3)
    if not np.isfinite(T).all():
        T = np.eye(4)
    T = icp(source, target, T, method="point_to_plane", max_distance=p.refine_distance,
            max_iterations=p.icp_max_iterations, voxel_size=p.icp_voxel_size, normal_radius=p.normal_radius)
    return T, time.perf_counter() - t0


def small_gicp_gicp(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """small_gicp GICP from identity (its own voxel downsampling, covariances from 10 neighbours)."""
    t0 = time.perf_counter()
    result = small_gicp.align(
        np.asarray(target, dtype=np.float64), np.asarray(source, dtype=np.float64),
        registration_type="GICP", downsampling_resolution=p.gicp_voxel_size,
        max_correspondence_distance=p.gicp_max_distance, num_threads=p.threads,
        max_iterations=p.icp_max_iterations,
    )
    return np.asarray(result.T_target_source).copy(), time.perf_counter() - t0


def truth_gicp(source: np.ndarray, target: np.ndarray, p: BaselineParams, truth: np.ndarray
               ) -> tuple[np.ndarray, float]:
    """A reference, not a method (it is given the answer): small_gicp GICP as `small_gicp_gicp`, started at the
    true pose `truth`: where the clouds' geometry, as GICP weighs it, settles next to the recorded pose. Where
    that leaves the success rule, the recorded pose and the depth disagree by more than the rule allows."""
    t0 = time.perf_counter()
    T = gicp(source, target, truth, max_distance=p.gicp_max_distance, max_iterations=p.icp_max_iterations,
             voxel_size=p.gicp_voxel_size, threads=p.threads)
    return T, time.perf_counter() - t0


def identity(source: np.ndarray, target: np.ndarray, p: BaselineParams) -> tuple[np.ndarray, float]:
    """No registration: the error of doing nothing (the motion in the pair)."""
    return np.eye(4), 0.0


BASELINES: dict[str, BaselineFn] = {
    "icp-p2p": icp_point_to_point,
    "icp-p2plane": icp_point_to_plane,
    "fpfh+fgr": fpfh_fgr,
    "fpfh+ransac": fpfh_ransac,
    "fpfh+ransac+icp": fpfh_ransac_icp,
    "fpfh+ransac+icp-accurate": fpfh_ransac_icp_accurate,
    "kiss-matcher+p2plane": kiss_matcher_p2plane,
    "small_gicp": small_gicp_gicp,
}
