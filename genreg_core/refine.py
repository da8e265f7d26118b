"""Pipeline stage "refine": the one ICP wrapper of genreg (Open3D, small_gicp) and the refinement guard.

Every ICP in the project (the pipeline's refine stage and its guard, the benchmark baselines, the replay
harness's reference) calls `icp`. The pipeline runs the method `RefineConfig.method` names through the
refinement registry (`genreg_core.refinement.REFINEMENTS`): `refine` and `guard_icp` call its function,
one of `point_to_point`, `point_to_plane` and `gicp_on_index` below. Transforms are target_from_source
(`genreg_core.geometry`), in the units of the points given.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import small_gicp

from genreg_core.config import RefineConfig
from genreg_core.refinement import refinement
from genreg_core.score import NORMAL_NEIGHBOURS, TargetIndex


def o3d_cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    """An Open3D cloud of the finite rows of an (N, 3) array (float64 copy)."""
    points = np.asarray(points, dtype=np.float64)
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


def downsample(cloud: o3d.geometry.PointCloud, voxel_size: float) -> o3d.geometry.PointCloud:
    """Open3D voxel-grid downsampling (centroid per voxel); 0 keeps the cloud."""
    return cloud.voxel_down_sample(voxel_size) if voxel_size > 0 else cloud


def estimate_normals(cloud: o3d.geometry.PointCloud, radius: float | None = None) -> o3d.geometry.PointCloud:
    """Normals from `score.NORMAL_NEIGHBOURS` neighbours, or from a radius search (at most 30) when `radius` is given."""
    search = (o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS) if radius is None
              else o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    cloud.estimate_normals(search)
    return cloud


def icp(
    source: np.ndarray | o3d.geometry.PointCloud,
    target: np.ndarray | o3d.geometry.PointCloud | TargetIndex,
    init: np.ndarray | None = None,
    *,
    method: str = "point_to_plane",
    max_distance: float,
    max_iterations: int,
    voxel_size: float = 0.0,
    normal_radius: float | None = None,
    fine: tuple[float, int] | None = None,
) -> np.ndarray:
    """ICP from `init` (identity if None): the 4x4 target_from_source it converges to; with `fine` =
    (distance, iterations), that many more iterations from there at that distance (the clouds prepared once).

    `method`: Open3D's "point_to_point" or "point_to_plane" (target normals by `estimate_normals`, unless
    the target cloud already has them), or small_gicp's "gicp" (arrays only; covariances from its default
    neighbourhoods). Both clouds are voxel-downsampled first when `voxel_size` > 0. A `TargetIndex` target
    is its points; GICP also uses its small_gicp cloud and k-d tree instead of building others.
    """
    if method == "gicp" and isinstance(target, TargetIndex) and voxel_size == 0:
        return gicp_target(target).align(np.asarray(source, dtype=np.float64), init, max_distance=max_distance,
                                         max_iterations=max_iterations, fine=fine)
    target = target.points if isinstance(target, TargetIndex) else target
    if method == "gicp":
        return gicp(np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64), init,
                    max_distance=max_distance, max_iterations=max_iterations, voxel_size=voxel_size, fine=fine)
    reg = o3d.pipelines.registration
    src = source if isinstance(source, o3d.geometry.PointCloud) else o3d_cloud(source)
    tgt = target if isinstance(target, o3d.geometry.PointCloud) else o3d_cloud(target)
    src, tgt = downsample(src, voxel_size), downsample(tgt, voxel_size)
    if method == "point_to_plane":
        if not tgt.has_normals():
            estimate_normals(tgt, normal_radius)
        estimation = reg.TransformationEstimationPointToPlane()
    elif method == "point_to_point":
        estimation = reg.TransformationEstimationPointToPoint()
    else:
        raise ValueError(f"icp method must be 'point_to_point' or 'point_to_plane', got {method!r}")
    T = np.eye(4) if init is None else init
    for distance, iterations in stages(max_distance, max_iterations, fine):
        T = reg.registration_icp(src, tgt, distance, T, estimation,
                                 reg.ICPConvergenceCriteria(max_iteration=iterations)).transformation
    return np.asarray(T).copy()


class VoxelTarget:
    """A target cloud prepared once for small_gicp's VGICP: its points' Gaussians (mean, covariance) merged
    per voxel of `resolution`. Correspondences are voxel lookups, not k-d tree searches, so a source aligns
    against a map of millions of points in milliseconds (coarser than GICP: one Gaussian per voxel)."""

    def __init__(self, target: GICPTarget, resolution: float) -> None:
        """`target`: the points with their covariances (`gicp_target`)."""
        self.voxels = small_gicp.GaussianVoxelMap(resolution)
        self.voxels.insert(target.cloud)
        self.neighbours = target.neighbours

    def align(self, source: np.ndarray, init: np.ndarray, *, max_iterations: int, threads: int = 1
              ) -> tuple[np.ndarray, float]:
        """VGICP of `source` (its covariances from the target's neighbour count) from `init`: the 4x4
        target_from_source, and the share of the source's points that met a voxel's Gaussian under it."""
        cloud = small_gicp.PointCloud(np.ascontiguousarray(source, dtype=np.float64))
        tree = small_gicp.KdTree(cloud, num_threads=1)
        small_gicp.estimate_covariances(cloud, tree, num_neighbors=self.neighbours, num_threads=1)
        result = small_gicp.align(self.voxels, cloud, np.asarray(init, float), max_iterations=max_iterations,
                                  num_threads=threads)
        return np.asarray(result.T_target_source).copy(), result.num_inliers / max(len(source), 1)


class GICPTarget:
    """A target cloud prepared once for small_gicp's GICP (its k-d tree and point covariances), to align
    many sources against (a map). Each source is prepared the same way on the same `threads` (per point:
    the same result on any number of threads)."""

    def __init__(self, target: np.ndarray | TargetIndex, *, neighbours: int = 10, threads: int = 1,
                 build_threads: int | None = None) -> None:
        """`target`: the points, or their `TargetIndex`, whose small_gicp cloud and k-d tree are used instead
        of building them (a map's points held once); `build_threads`: the threads that build the target's tree
        and covariances (default `threads`: a map prepared once may take more than each source's alignment)."""
        build = build_threads or threads
        if isinstance(target, TargetIndex):
            self.cloud, self.tree = target.cloud, target.tree
        else:
            self.cloud = small_gicp.PointCloud(np.ascontiguousarray(target, dtype=np.float64))
            self.tree = small_gicp.KdTree(self.cloud, num_threads=build)
        self.neighbours = neighbours
        self.threads = threads
        small_gicp.estimate_covariances(self.cloud, self.tree, num_neighbors=neighbours, num_threads=build)

    def align(self, source: np.ndarray, init: np.ndarray | None = None, *, max_distance: float, max_iterations: int,
              threads: int = 1, fine: tuple[float, int] | None = None) -> np.ndarray:
        """GICP of `source` (its k-d tree and covariances from as many neighbours as the target's, on the
        target's threads) from `init`: the 4x4 target_from_source; with `fine` = (distance, iterations), that
        many more at that distance. The alignment runs on `threads` (more than one changes its last bits
        from run to run: the order of its sums)."""
        cloud = small_gicp.PointCloud(np.ascontiguousarray(source, dtype=np.float64))
        tree = small_gicp.KdTree(cloud, num_threads=self.threads)
        small_gicp.estimate_covariances(cloud, tree, num_neighbors=self.neighbours, num_threads=self.threads)
        T = np.eye(4) if init is None else np.asarray(init, float)
        for distance, iterations in stages(max_distance, max_iterations, fine):
            T = small_gicp.align(self.cloud, cloud, self.tree, T, registration_type="GICP",
                                 max_correspondence_distance=distance, num_threads=threads,
                                 max_iterations=iterations).T_target_source
        return np.asarray(T).copy()


def gicp_target(index: TargetIndex) -> GICPTarget:
    """An index's points prepared for GICP (covariances, its k-d tree, on the index's threads), once per
    index: every candidate pose of a pair, every scan tracked in one local map, aligns against the same
    target."""
    if index.gicp is None:
        index.gicp = GICPTarget(index, threads=index.threads)
    return index.gicp


def gicp(source: np.ndarray, target: np.ndarray, init: np.ndarray | None = None, *, max_distance: float,
         max_iterations: int, voxel_size: float = 0.0, threads: int = 1, neighbours: int = 10,
         fine: tuple[float, int] | None = None) -> np.ndarray:
    """small_gicp's GICP from `init`: the 4x4 target_from_source; `fine` as `icp`'s. Both clouds are
    voxel-downsampled by small_gicp when `voxel_size` > 0; point covariances from `neighbours` nearest
    neighbours."""
    T = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)
    if voxel_size > 0:
        for distance, iterations in stages(max_distance, max_iterations, fine):
            T = small_gicp.align(target, source, T, registration_type="GICP", downsampling_resolution=voxel_size,
                                 max_correspondence_distance=distance, num_threads=threads,
                                 max_iterations=iterations).T_target_source
        return np.asarray(T).copy()
    return GICPTarget(target, neighbours=neighbours, threads=threads).align(
        source, T, max_distance=max_distance, max_iterations=max_iterations, threads=threads, fine=fine)


def stages(max_distance: float, max_iterations: int, fine: tuple[float, int] | None) -> list[tuple[float, int]]:
    """ICP's (distance, iterations) stages: the wide one, then `fine` if given."""
    return [(max_distance, max_iterations), *([] if fine is None else [fine])]


def point_to_point(source: np.ndarray, target: np.ndarray | TargetIndex, init: np.ndarray, *, max_distance: float,
                   max_iterations: int, fine: tuple[float, int] | None = None) -> np.ndarray:
    """The registry's "point_to_point": Open3D point-to-point ICP (`icp`) against the target's points."""
    return icp(source, target, init, method="point_to_point", max_distance=max_distance,
               max_iterations=max_iterations, fine=fine)


def point_to_plane(source: np.ndarray, target: np.ndarray | o3d.geometry.PointCloud, init: np.ndarray, *,
                   max_distance: float, max_iterations: int, fine: tuple[float, int] | None = None) -> np.ndarray:
    """The registry's "point_to_plane": Open3D point-to-plane ICP (`icp`) against a cloud carrying its normals
    (`PreparedPair.plane_target`; an array gets them by `estimate_normals`)."""
    return icp(source, target, init, method="point_to_plane", max_distance=max_distance,
               max_iterations=max_iterations, fine=fine)


def gicp_on_index(source: np.ndarray, target: np.ndarray | TargetIndex, init: np.ndarray, *, max_distance: float,
                  max_iterations: int, fine: tuple[float, int] | None = None) -> np.ndarray:
    """The registry's "gicp": small_gicp's GICP (`icp`) against a `TargetIndex`, whose k-d tree it searches and
    whose covariances it prepares once for every candidate of a pair (`gicp_target`; an array is prepared
    afresh)."""
    return icp(source, target, init, method="gicp", max_distance=max_distance, max_iterations=max_iterations,
               fine=fine)


def refine(src: np.ndarray, tgt: object, T_init: np.ndarray, cfg: RefineConfig) -> np.ndarray:
    """The pipeline's refine stage: `cfg.max_iterations` iterations of the registry's method `cfg.method` from
    T_init, then its tight stage (`tight_stage`); T_init itself for "none". `tgt`: the method's
    `Refinement.target` of the pair (or the target's points)."""
    method = refinement(cfg.method)
    if not method.refines:
        return T_init
    return method.function()(src, tgt, T_init, max_distance=cfg.max_correspondence_distance,
                             max_iterations=cfg.max_iterations, fine=tight_stage(cfg))


def tight_stage(cfg: RefineConfig) -> tuple[float, int] | None:
    """(distance, iterations) of the refinement's tight stage, `cfg.fine_iterations` at `cfg.fine_fraction` of
    its correspondence distance, or None when the fraction is 1."""
    return None if cfg.fine_fraction >= 1.0 else (cfg.fine_fraction * cfg.max_correspondence_distance,
                                                  cfg.fine_iterations)


def guard_icp(src: np.ndarray, tgt: object, cfg: RefineConfig) -> np.ndarray:
    """The refinement guard's candidate (no initial guess given): the registry's method `cfg.method` (one that
    refines) from identity with the guard's wide cut-off and iterations, then the tight stage."""
    return refinement(cfg.method).function()(src, tgt, np.eye(4), max_distance=cfg.guard_distance,
                                             max_iterations=cfg.guard_iterations, fine=tight_stage(cfg))
