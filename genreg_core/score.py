"""Pipeline stage "score": how well a transform explains the pair (fitness, inlier RMSE, confidence).

fitness: the share of (refinement-resolution) source points that land within `FITNESS_SPACINGS` target
point spacings of a target point; inlier ratio: the share of the generated correspondences (both
directions) that the transform maps within PDSAC's inlier threshold; confidence: their geometric mean.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from genreg_core.refine import o3d_cloud

FITNESS_SPACINGS = 3.0  # fitness counts a source point as overlapping within this many target spacings
# pose_covariance's model error, calibrated on redkitchen training pairs by scripts/calibrate_covariance.py
# (MODEL_CARD.md): the Gauss-Newton covariance times COVARIANCE_INFLATION (residuals of neighbouring points
# are correlated) plus a floor of COVARIANCE_FLOOR_M (m) and COVARIANCE_FLOOR_RAD (rad) standard deviation
# per axis (errors that no residual shows: depth distortion, the ground truth's own error).
COVARIANCE_INFLATION = 44.7
COVARIANCE_FLOOR_M = 0.0033
COVARIANCE_FLOOR_RAD = 0.0023


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest neighbour in the same cloud (its sampling density)."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


def fitness_distance(target: np.ndarray) -> float:
    """The distance within which a moved source point counts as overlapping `target`."""
    return FITNESS_SPACINGS * point_spacing(target)


def overlap_fitness(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, threshold: float) -> tuple[float, float]:
    """Open3D's fitness (share of moved source points with a target point within `threshold`) and RMSE."""
    ev = o3d.pipelines.registration.evaluate_registration(o3d_cloud(src), o3d_cloud(tgt), threshold, T)
    return float(ev.fitness), float(ev.inlier_rmse)


def confidence(fitness: float, inlier_ratio: float) -> float:
    """In [0, 1]: the geometric mean of fitness and inlier ratio."""
    return float(np.sqrt(fitness * inlier_ratio))


def pose_covariance(moved: np.ndarray, target: np.ndarray, origin: np.ndarray, max_distance: float,
                    inflation: float = 1.0, floor: tuple[float, float] = (0.0, 0.0)) -> np.ndarray | None:
    """6x6 covariance of a pose, in ROS order (x, y, z, rotation about x, y, z), from the point-to-plane
    residuals of the aligned clouds; None when fewer than 12 correspondences remain.

    Model: each moved source point x_i and its nearest target point q_i (within `max_distance`) with the
    target normal n_i give r_i = n_i . (x_i - q_i). The pose is perturbed in the parent (target) frame:
    R' = exp(dtheta) R, t' = t + dt, so dr_i/d(dt, dtheta) = (n_i, (x_i - origin) x n_i) with `origin`
    the pose's position t. Gauss-Newton: C = inflation * s^2 (J^T J)^-1 + diag(f_t^2 I, f_r^2 I), with
    s^2 = sum r_i^2 / (n - 6) and `floor` = (f_t, f_r). The residuals of neighbouring points are not
    independent, so the plain formula is over-confident; `inflation` and `floor` are calibrated on
    training pairs (MODEL_CARD.md). Units: those of the points (m) and radians.
    """
    distances, index = cKDTree(target).query(moved, distance_upper_bound=max_distance)
    found = np.isfinite(distances)
    if found.sum() < 12:
        return None
    cloud = o3d_cloud(target)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    normals = np.asarray(cloud.normals)[index[found]]
    x = moved[found]
    r = np.einsum("ij,ij->i", normals, x - target[index[found]])
    J = np.concatenate([normals, np.cross(x - origin, normals)], axis=1)
    H = J.T @ J
    if np.linalg.cond(H) > 1e12:
        return None
    sigma2 = float(r @ r) / max(len(r) - 6, 1)
    C = inflation * sigma2 * np.linalg.inv(H) + np.diag([floor[0] ** 2] * 3 + [floor[1] ** 2] * 3)
    return 0.5 * (C + C.T)
