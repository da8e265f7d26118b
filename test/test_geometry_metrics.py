"""Geometry and metrics against independent computations (scipy, Open3D, brute force)."""

import itertools

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy.spatial.transform import Rotation

from genreg_core.geometry import (
    apply_transform,
    denormalize_transform,
    extrapolate,
    invert_transform,
    kabsch,
    make_transform,
    normalize_pair,
    params_to_transform,
    random_transform,
)
from genreg_core.metrics import (
    chamfer_distance,
    earth_movers_distance,
    rotation_error_deg,
    transform_errors,
    translation_error,
)


def test_random_transform_follows_the_paper_protocol():
    rng = np.random.default_rng(0)
    Ts = [random_transform(rng) for _ in range(2000)]
    angles = np.array([np.rad2deg(np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec())) for T in Ts])
    shifts = np.array([np.linalg.norm(T[:3, 3]) for T in Ts])
    assert angles.max() <= 45.0 + 1e-9 and angles.min() >= 0.0
    assert 20.0 < angles.mean() < 25.0  # uniform on [0, 45]
    assert shifts.max() <= 0.8 + 1e-12 and 0.35 < shifts.mean() < 0.45
    axes = np.array([Rotation.from_matrix(T[:3, :3]).as_rotvec() for T in Ts])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    assert np.abs(axes.mean(axis=0)).max() < 0.06  # isotropic axis
    for T in Ts[:20]:
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_apply_and_invert_transform_column_convention():
    rng = np.random.default_rng(1)
    T = random_transform(rng)
    x = rng.normal(size=(10, 3))
    expected = (T[:3, :3] @ x.T).T + T[:3, 3]  # x' = R x + t
    assert np.allclose(apply_transform(T, x), expected)
    assert np.allclose(apply_transform(invert_transform(T), apply_transform(T, x)), x)
    Tt = torch.tensor(T)
    assert torch.allclose(invert_transform(Tt), torch.tensor(np.linalg.inv(T)))


def test_kabsch_matches_scipy_align_vectors():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3))
    T = random_transform(rng)
    dst = apply_transform(T, src) + rng.normal(scale=0.01, size=src.shape)
    est = kabsch(torch.tensor(src), torch.tensor(dst)).numpy()
    src_c, dst_c = src - src.mean(0), dst - dst.mean(0)
    R_ref, _ = Rotation.align_vectors(dst_c, src_c)
    assert rotation_error_deg(est[:3, :3], R_ref.as_matrix()) < 1e-6
    assert np.isclose(np.linalg.det(est[:3, :3]), 1.0)


def test_kabsch_returns_a_proper_rotation_for_a_reflection():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror: the best proper rotation must still have det +1
    est = kabsch(torch.tensor(src), torch.tensor(dst)).numpy()
    assert np.isclose(np.linalg.det(est[:3, :3]), 1.0)


def test_params_to_transform_matches_scipy_rotvec():
    rotvec = np.array([0.3, -0.2, 0.5])
    T = params_to_transform(torch.tensor(np.r_[rotvec, 1.0, 2.0, 3.0])[None])[0].numpy()
    assert np.allclose(T[:3, :3], Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    assert np.allclose(T[:3, 3], [1, 2, 3])


def test_normalize_pair_keeps_the_relative_pose():
    rng = np.random.default_rng(4)
    src = rng.uniform(-5, 20, size=(200, 3))
    T = random_transform(rng, 45, 3.0)
    tgt = apply_transform(T, src)
    s_n, t_n, T_n, offset, scale = normalize_pair(src, tgt, T)
    assert np.allclose(s_n.min(axis=0), 0.0, atol=1e-6)  # the source fills the unit box
    assert np.isclose((s_n.max(axis=0) - s_n.min(axis=0)).max(), 1.0, atol=1e-6)
    assert np.allclose(apply_transform(T_n, s_n), t_n, atol=1e-5)
    assert np.allclose(denormalize_transform(T_n, offset, scale), T, atol=1e-9)


def test_chamfer_matches_open3d():
    rng = np.random.default_rng(5)
    a, b = rng.random((300, 3)), rng.random((250, 3))
    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a))
    pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b))
    ref = 0.5 * (np.mean(pa.compute_point_cloud_distance(pb)) + np.mean(pb.compute_point_cloud_distance(pa)))
    assert np.isclose(chamfer_distance(a, b), ref, rtol=1e-9)


def test_emd_matches_brute_force_over_permutations():
    rng = np.random.default_rng(6)
    a, b = rng.random((6, 3)), rng.random((6, 3))
    best = min(np.mean(np.linalg.norm(a - b[list(p)], axis=1)) for p in itertools.permutations(range(6)))
    assert np.isclose(earth_movers_distance(a, b), best)
    with pytest.raises(ValueError):
        earth_movers_distance(a, b[:5])


def test_rotation_and_translation_errors_match_scipy():
    rng = np.random.default_rng(7)
    R1, R2 = Rotation.random(random_state=1), Rotation.random(random_state=2)
    expected = np.rad2deg((R1 * R2.inv()).magnitude())
    assert np.isclose(rotation_error_deg(R1.as_matrix(), R2.as_matrix()), expected, atol=1e-6)
    t1, t2 = rng.normal(size=3), rng.normal(size=3)
    assert np.isclose(translation_error(t1, t2), np.linalg.norm(t1 - t2))
    T = random_transform(rng)
    assert transform_errors(T, T) == pytest.approx((0.0, 0.0), abs=1e-6)


def test_rotation_error_is_accurate_for_tiny_angles():
    R = Rotation.from_rotvec([0.0, 0.0, np.deg2rad(0.01)]).as_matrix()
    assert np.isclose(rotation_error_deg(R, np.eye(3)), 0.01, rtol=1e-6)
    assert np.isclose(rotation_error_deg(Rotation.from_rotvec([np.pi * 0.999, 0, 0]).as_matrix(), np.eye(3)), 179.82)


def test_kabsch_gradient_is_finite_for_degenerate_sets_and_flows_for_good_ones():
    import torch

    from genreg_core.geometry import kabsch

    src = torch.rand(2, 4, 3, dtype=torch.float64)
    dst = torch.rand(2, 4, 3, dtype=torch.float64)
    dst[0] = dst[0, :1].expand(4, 3).clone()  # every point of set 0 picked the same match
    dst.requires_grad_(True)
    kabsch(src, dst).sum().backward()
    assert torch.isfinite(dst.grad).all()
    # Set 0: only the translation's centroid term (d sum(t) / d dst = 1/4 each); set 1 also rotates.
    assert torch.allclose(dst.grad[0], torch.full((4, 3), 0.25, dtype=torch.float64))
    assert not torch.allclose(dst.grad[1], torch.full((4, 3), 0.25, dtype=torch.float64))


def test_det3_equals_torch_linalg_det():
    from genreg_core.geometry import det3

    M = torch.randn(4, 50, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(det3(M), torch.linalg.det(M), rtol=1e-12, atol=1e-12)


def test_extrapolate_goes_on_along_a_constant_twist():
    """A vehicle on a constant twist (a helix: turning while it drives and climbs): its pose at time t is
    T0 expm(t xi), so from the poses at t = 1 and 2 the pose at 2 + r is predicted for any r (scipy's expm
    and the twist are the truth)."""
    from scipy.linalg import expm

    rng = np.random.default_rng(3)
    T0 = make_transform(Rotation.random(random_state=3).as_matrix(), rng.normal(size=3))
    xi = np.zeros((4, 4))
    w, v = np.array([0.02, -0.03, 0.4]), np.array([1.8, 0.2, 0.05])
    xi[:3, :3] = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]
    xi[:3, 3] = v
    pose = [T0 @ expm(t * xi) for t in (1.0, 2.0)]
    for r in (0.0, 0.5, 1.0, 2.0, 2.5, -0.3, -1.0):  # whole motions (a matrix power), fractions, interpolation
        np.testing.assert_allclose(extrapolate(pose[0], pose[1], r), T0 @ expm((2.0 + r) * xi), atol=1e-9)
    # standing still: the pose stays, whatever the ratio
    np.testing.assert_allclose(extrapolate(pose[1], pose[1], 3.0), pose[1], atol=1e-12)
    # poses a little off orthonormal (as ICP returns them) give a rigid prediction, however often repeated
    drift = np.eye(4)
    drift[:3, :3] += 3e-5 * rng.normal(size=(3, 3))
    a, b = pose[0] @ drift, pose[1] @ drift
    for _ in range(200):
        a, b = b, extrapolate(a, b, 1.0) @ drift
    R = extrapolate(a, b, 1.0)[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
