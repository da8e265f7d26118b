"""Pipeline stage "fallback" (opt-in): classical global registration when GenReg stays unsure.

Open3D FPFH features and feature-matching RANSAC, the classical global method of the field; the
benchmark baselines (`genreg_bench.baselines`) call the same `fpfh_ransac`. Lengths are in the
clouds' units; the pipeline calls it on the prepared pair's refinement clouds in their normalised frame
(the source's robust extent is 1), with `FallbackConfig`'s fractions of that extent. Transforms are
target_from_source (`genreg_core.geometry`).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from genreg_core.config import FallbackConfig
from genreg_core.refine import downsample, estimate_normals, o3d_cloud

reg = o3d.pipelines.registration


def fpfh(points: np.ndarray, voxel_size: float, normal_radius: float, fpfh_radius: float
         ) -> tuple[o3d.geometry.PointCloud, reg.Feature]:
    """The voxel-downsampled cloud (0: as given) with radius normals, and its FPFH features (at most 100
    neighbours)."""
    cloud = estimate_normals(downsample(o3d_cloud(points), voxel_size), normal_radius)
    feature = reg.compute_fpfh_feature(cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=fpfh_radius, max_nn=100))
    return cloud, feature


def fpfh_ransac(source: np.ndarray, target: np.ndarray, *, voxel_size: float, normal_radius: float,
                fpfh_radius: float, distance: float, max_iterations: int = 100_000, confidence: float = 0.999,
                seed: int = 0) -> np.ndarray:
    """FPFH + Open3D feature RANSAC (mutual filter, 3-point samples, edge-length and distance checkers at
    `distance`): the 4x4 target_from_source it finds. Multi-threaded RANSAC is not bit-reproducible."""
    src, src_f = fpfh(source, voxel_size, normal_radius, fpfh_radius)
    tgt, tgt_f = fpfh(target, voxel_size, normal_radius, fpfh_radius)
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_feature_matching(
        src, tgt, src_f, tgt_f, True, distance, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(max_iterations, confidence),
    )
    return np.asarray(result.transformation).copy()


def fallback(source: np.ndarray, target: np.ndarray, cfg: FallbackConfig) -> np.ndarray:
    """The pipeline's fallback on normalised clouds (lengths: fractions of the source's robust extent)."""
    return fpfh_ransac(source, target, voxel_size=cfg.voxel_size, normal_radius=cfg.normal_radius,
                       fpfh_radius=cfg.fpfh_radius, distance=cfg.distance, seed=cfg.seed)
