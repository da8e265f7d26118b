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
