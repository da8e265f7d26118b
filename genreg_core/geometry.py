"""SE(3) helpers shared by the model, PDSAC, data and the registration API.

Conventions (everywhere in genreg):
- Points are rows: a cloud is an (N, 3) array, batched clouds are (B, N, 3).
- Transforms are 4x4 homogeneous matrices acting on column vectors: x' = R x + t.
  Applied to row-stored points this reads X' = X R^T + t (see `apply_transform`).
- A transform named `T_ab` maps points expressed in frame b into frame a.
- Units are whatever the input carries (metres for sensor data, REP-103); angles are radians
  unless a name ends in `_deg`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from scipy.spatial.transform import RigidTransform, Rotation

from genreg_core import kernels

ArrayLike = np.ndarray | torch.Tensor


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = np.asarray(translation).reshape(3)
    return T


def kidnap_motion(rng: np.random.Generator, center: np.ndarray, max_angle_deg: float = 45.0,
                  max_translation: float = 0.5) -> np.ndarray:
    """The 4x4 motion x -> R (x - center) + center + t: R by an angle uniform in [0, max_angle_deg] about a
    uniformly random axis, t of uniformly random direction and length uniform in [0, max_translation]."""
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    angle = np.deg2rad(rng.uniform(0.0, max_angle_deg))
    R = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
    t = rng.uniform(0.0, max_translation) * direction / np.linalg.norm(direction)
    return make_transform(R, center - R @ center + t)


def invert_transform(T: ArrayLike) -> ArrayLike:
    """Inverse of a rigid transform (batched over leading dims): [R t]^-1 = [R^T, -R^T t]."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2) if isinstance(T, torch.Tensor) else np.swapaxes(R, -1, -2)
    inv = torch.zeros_like(T) if isinstance(T, torch.Tensor) else np.zeros_like(T)
    inv[..., :3, :3] = Rt
    inv[..., :3, 3:] = -(Rt @ t)
    inv[..., 3, 3] = 1.0
    return inv


def extrapolate(T_prev: np.ndarray, T_last: np.ndarray, ratio: float) -> np.ndarray:
    """Constant velocity: `T_last` moved on by the motion from `T_prev` to it (T_prev^-1 T_last, the same
    screw motion) taken `ratio` times; 0 gives T_last, 1 repeats the motion, -1 gives T_prev (between -1 and 0:
    the screw interpolation of the two). A whole number of motions is a matrix power; a fraction scales the
    motion's exponential coordinates (scipy's `RigidTransform.as_exp_coords`: 0.5 ms, where
    `fractional_matrix_power`'s Pade path takes 1-1.4 ms alone and about 16 ms inside the node). Both poses map
    the same moving frame into the same fixed one (T_map_scan of two scans). Their rotations are taken as the
    nearest rotations (scipy's `Rotation.from_matrix`), so the result is rigid however many poses were predicted
    from predictions (an ICP's pose drifts off orthonormal by ~1e-5)."""
    prev, last = rigid(T_prev), rigid(T_last)
    motion = invert_transform(prev) @ last
    ratio = float(ratio)
    if ratio.is_integer() and ratio >= 0:
        return rigid(last @ np.linalg.matrix_power(motion, int(ratio)))
    coords = RigidTransform.from_matrix(motion).as_exp_coords()
    return rigid(last @ RigidTransform.from_exp_coords(ratio * coords).as_matrix())


def moved_along(T: np.ndarray, direction: np.ndarray, distances: Sequence[float]) -> list[np.ndarray]:
    """T (4x4) with its translation moved by each of `distances` along the unit `direction` (its frame's)."""
    moved = []
    for d in distances:
        S = T.copy()
        S[:3, 3] += d * direction
        moved.append(S)
    return moved


def turned_about(T: np.ndarray, axis: np.ndarray, pivot: np.ndarray, angles: Sequence[float]) -> list[np.ndarray]:
    """T (4x4) turned by each of `angles` (radians) about the line through `pivot` along the unit `axis` (both in
    its frame's coordinates)."""
    turned = []
    for angle in angles:
        R = Rotation.from_rotvec(angle * np.asarray(axis, dtype=np.float64)).as_matrix()
        turned.append(make_transform(R, pivot - R @ pivot) @ T)
    return turned


def rigid(T: np.ndarray) -> np.ndarray:
    """A 4x4 transform (float64 copy) with its rotation replaced by the nearest rotation and its last row
    (0, 0, 0, 1)."""
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = Rotation.from_matrix(out[:3, :3]).as_matrix()
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def apply_transform(T: ArrayLike, points: ArrayLike) -> ArrayLike:
    """x' = R x + t for row-stored points; T (..., 4, 4) batches with points (..., N, 3).

    A single numpy cloud is transformed with three broadcast multiply-adds instead of a (N, 3) @ (3, 3)
    matrix product, which is slow for tall, thin arrays here (about 100 ms at 300k points).
    """
    R, t = T[..., :3, :3], T[..., :3, 3]
    if isinstance(T, torch.Tensor):
        return points @ R.transpose(-1, -2) + t[..., None, :]
    if np.ndim(T) == 2 and np.ndim(points) == 2:
        R = R.astype(points.dtype, copy=False) if points.dtype.kind == "f" else R
        out = points[:, 0:1] * R[:, 0] + t.astype(R.dtype)
        out += points[:, 1:2] * R[:, 1]
        out += points[:, 2:3] * R[:, 2]
        return out
    return points @ np.swapaxes(R, -1, -2) + t[..., None, :]


def rotation_angle(R: ArrayLike) -> ArrayLike:
    """Rotation angle in radians of (batched) 3x3 rotations: atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2).

    Accurate for small angles (unlike arccos of the trace) and tolerant of slightly non-orthonormal
    input such as poses stored as text.
    """
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    vee = [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]]
    if isinstance(R, torch.Tensor):
        return torch.atan2(torch.linalg.norm(torch.stack(vee, -1), dim=-1) / 2.0, (trace - 1.0) / 2.0)
    return np.arctan2(np.linalg.norm(np.stack(vee, -1), axis=-1) / 2.0, (trace - 1.0) / 2.0)


def random_transform(
    rng: np.random.Generator, max_angle_deg: float = 45.0, max_translation: float = 0.8
) -> np.ndarray:
    """The paper's random rigid transform (Sec. 4.1).

    Rotation: angle uniform in [0, max_angle_deg] about a uniformly random unit axis.
    Translation: uniformly random direction, magnitude uniform in [0, max_translation].
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(0.0, max_angle_deg))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    translation = direction * rng.uniform(0.0, max_translation)
    return make_transform(Rotation.from_rotvec(axis * angle).as_matrix(), translation)


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Differentiable Rodrigues formula: (..., 3) rotation vectors -> (..., 3, 3) matrices."""
    angle = torch.linalg.norm(rotvec, dim=-1, keepdim=True).clamp_min(1e-8)
    k = rotvec / angle
    zero = torch.zeros_like(k[..., 0])
    K = torch.stack(
        [zero, -k[..., 2], k[..., 1], k[..., 2], zero, -k[..., 0], -k[..., 1], k[..., 0], zero],
        dim=-1,
    ).reshape(*rotvec.shape[:-1], 3, 3)
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(K)
    return eye + s * K + (1.0 - c) * (K @ K)


def params_to_transform(params: torch.Tensor) -> torch.Tensor:
    """(..., 6) = (rotation vector, translation) -> (..., 4, 4) rigid transforms (differentiable)."""
    T = torch.zeros(*params.shape[:-1], 4, 4, dtype=params.dtype, device=params.device)
    T[..., :3, :3] = axis_angle_to_matrix(params[..., :3])
    T[..., :3, 3] = params[..., 3:]
    T[..., 3, 3] = 1.0
    return T


def det3(M: torch.Tensor) -> torch.Tensor:
    """Determinants of (..., 3, 3) matrices by the rule of Sarrus: elementwise, where torch.linalg.det's
    batched LU costs ~1.5 ms on PDSAC's 1024 hypotheses."""
    a, b, c = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    d, e, f = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    g, h, i = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def kabsch(
    source: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Weighted least-squares rigid transform with target ~ R source + t (proper, det R = +1).

    source, target: (..., K, 3); weights: (..., K) non-negative or None. Returns (..., 4, 4).
    Batched over leading dims and differentiable (SVD of the 3x3 cross-covariance); sets with equal
    singular values (degenerate, e.g. coinciding points) get no gradient instead of a NaN one. Where
    `kernels.usable` (inference on the CPU) the same fit runs as compiled scalar code (`kernels.fit_rigid`: Horn's
    quaternion method, float64 inside; a set without weight gets identity).
    """
    if kernels.usable(source, target, weights):
        lead = source.shape[:-2]
        w = torch.ones(source.shape[:-1]) if weights is None else weights.expand(source.shape[:-1])
        rows = [x.detach().to(source.dtype).reshape(-1, *x.shape[len(lead):]).contiguous().numpy()
                for x in (source, target, w)]
        return torch.from_numpy(kernels.fit_rigid(*rows)).to(source.dtype).reshape(*lead, 4, 4)
    if weights is None:
        weights = torch.ones(source.shape[:-1], dtype=source.dtype, device=source.device)
    w = weights / weights.sum(dim=-1, keepdim=True).clamp_min(1e-12)
    mu_s = (w[..., None] * source).sum(dim=-2)
    mu_t = (w[..., None] * target).sum(dim=-2)
    cov = ((source - mu_s[..., None, :]) * w[..., None]).transpose(-1, -2) @ (target - mu_t[..., None, :])
    if cov.requires_grad:  # the SVD's gradient is 1 / (s_i^2 - s_j^2): not finite for equal singular
        with torch.no_grad():  # values (e.g. a minimal set whose points coincide); no gradient from those
            sv = torch.linalg.svdvals(cov)
            gaps = torch.stack([sv[..., 0] - sv[..., 1], sv[..., 1] - sv[..., 2]], dim=-1).amin(dim=-1)
            degenerate = gaps <= 1e-6 * sv[..., 0].clamp_min(1e-12)
        cov = torch.where(degenerate[..., None, None], cov.detach(), cov)
    U, _, Vh = torch.linalg.svd(cov)
    d = torch.sign(det3(Vh) * det3(U))  # det(V U^T): U, V orthogonal, so +-1
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=source.dtype, device=source.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = mu_t - (R @ mu_s[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def unit_box_normalization(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Offset and scale that put a cloud into the unit box [0, 1]^3 (aspect kept).

    Returns (offset, scale) with normalised = (points - offset) / scale. Pass the union of two
    clouds to normalise them jointly, which keeps their relative pose (rotation unchanged,
    translation divided by scale).
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    scale = float(max((hi - lo).max(), 1e-12))
    return lo, scale


def normalize_pair(
    source: np.ndarray, target: np.ndarray, T_target_source: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, float]:
    """Normalise a pair jointly with one similarity taken from the source's bounding box.

    x_n = (x - offset) / scale for both clouds, so the source fills the unit box [0, 1]^3 as in
    training. A transform target_from_source becomes R_n = R, t_n = (t + R offset - offset) / scale.
    Returns (source_n, target_n, T_n or None, offset, scale).
    """
    offset, scale = unit_box_normalization(source)
    src_n = ((source - offset) / scale).astype(np.float32)
    tgt_n = ((target - offset) / scale).astype(np.float32)
    T_n = None
    if T_target_source is not None:
        T_n = np.array(T_target_source, dtype=np.float64)
        T_n[:3, 3] = (T_n[:3, 3] + T_n[:3, :3] @ offset - offset) / scale
    return src_n, tgt_n, T_n, offset, scale


def denormalize_transform(T_n: np.ndarray, offset: np.ndarray, scale: float) -> np.ndarray:
    """Inverse of the translation mapping in `normalize_pair`: t = scale t_n + offset - R offset."""
    T = np.array(T_n, dtype=np.float64)
    T[:3, 3] = scale * T[:3, 3] + offset - T[:3, :3] @ offset
    return T
