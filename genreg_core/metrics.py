"""Registration and generation metrics (numpy/scipy; inputs are (N, 3) clouds and 4x4 transforms).

- Chamfer distance (CD): mean nearest-neighbour distance, averaged over both directions.
- Rotation error (RE): isotropic, the angle of R_est R_gt^T, in degrees.
- Translation error (TE): Euclidean norm of t_est - t_gt, in the clouds' units.
- EMD: exact earth mover's distance by optimal assignment (equal sizes), mean matched distance.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from genreg_core.geometry import rotation_angle

EMD_MAX_POINTS = 2048


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """0.5 * (mean_a min_b |a - b| + mean_b min_a |b - a|), Euclidean (not squared)."""
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Isotropic rotation error: angle of R_est R_gt^T in degrees."""
    return float(np.rad2deg(rotation_angle(np.asarray(R_est) @ np.asarray(R_gt).T)))


def translation_error(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Euclidean norm |t_est - t_gt| in the units of the clouds."""
    return float(np.linalg.norm(np.asarray(t_est).reshape(3) - np.asarray(t_gt).reshape(3)))


def transform_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(RE in degrees, TE) between two 4x4 transforms."""
    return (
        rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]),
        translation_error(T_est[:3, 3], T_gt[:3, 3]),
    )


def earth_movers_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Exact EMD: min over bijections phi of mean |a_i - b_phi(i)|, by the Hungarian method."""
    if a.shape != b.shape:
        raise ValueError(f"EMD needs clouds of equal size, got {a.shape} and {b.shape}")
    if len(a) > EMD_MAX_POINTS:
        raise ValueError(f"exact EMD is limited to {EMD_MAX_POINTS} points, got {len(a)}")
    cost = cdist(a, b)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())
