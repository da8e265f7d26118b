"""The fast paths of stage "prepare" and of the scores, against independent truth: the seeded subsample
draw, the finite-row mask, the float32 aligned cloud, and the shared k-d tree's fitness, spacing, normals
and covariance (against Open3D, scipy and LAPACK). Behaviour only, never timings."""

from __future__ import annotations

import warnings

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from test_model import SMALL

from genreg_core import kernels
from genreg_core.geometry import apply_transform, random_transform
from genreg_core.metrics import transform_errors
from genreg_core.model import GenRegNet
from genreg_core.prepare import sample_indices, transform_rows, validate_cloud
from genreg_core.registration import Registrar
from genreg_core.score import (
    TargetIndex,
    overlap_fitness,
    plane_normals,
    point_spacing,
    pose_covariance,
)


def _surface(n: int, seed: int = 0) -> np.ndarray:
    """A smooth curved sheet with a little thickness noise (every neighbourhood has a clear normal)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-1, 1, (n, 2))
    z = 0.3 * np.sin(2 * uv[:, 0]) * np.cos(uv[:, 1]) + rng.normal(scale=0.002, size=n)
    return np.column_stack([uv, z])


@pytest.mark.parametrize("count, n", [(270_000, 5000), (100_000, 512), (3000, 1000), (1000, 1000)])
def test_draw_without_replacement_is_seeded_exact_and_in_range(count, n):
    a, b = (sample_indices(count, n, np.random.default_rng(7)) for _ in range(2))
    np.testing.assert_array_equal(a, b)  # seeded
    assert len(a) == n and len(np.unique(a)) == n and a.min() >= 0 and a.max() < count
    assert not np.array_equal(a, sample_indices(count, n, np.random.default_rng(8)))
    ordered = sample_indices(count, n, np.random.default_rng(7), ordered=True)
    assert len(np.unique(ordered)) == n and (np.diff(ordered) > 0).all()


def test_draw_with_fewer_points_than_wanted_keeps_every_point():
    a = sample_indices(300, 512, np.random.default_rng(0))
    assert len(a) == 512 and set(a.tolist()) == set(range(300))


@pytest.mark.parametrize("count, n", [(1000, 50), (400, 150)])  # the draw-and-deduplicate and permutation paths
def test_draw_is_uniform_over_rows_and_positions(count, n):
    """Every row equally likely to be drawn, and in random order: each row's count over many draws and
    the first position's row stay within 5 standard deviations of uniform."""
    rng = np.random.default_rng(1)
    trials = 4000
    draws = np.stack([sample_indices(count, n, rng) for _ in range(trials)])
    hits = np.bincount(draws.ravel(), minlength=count)
    p = n / count
    assert np.abs(hits - trials * p).max() < 5 * np.sqrt(trials * p * (1 - p)) + 1
    first = np.bincount(draws[:, 0] * 10 // count, minlength=10)  # the first row, by tenths of the cloud
    assert np.abs(first - trials / 10).max() < 5 * np.sqrt(trials * 0.1 * 0.9)


def test_finite_mask_matches_brute_force_and_all_finite_input_is_not_copied():
    rng = np.random.default_rng(2)
    points = rng.normal(size=(5000, 3)).astype(np.float32)
    rows, cols = rng.integers(0, 5000, 300), rng.integers(0, 3, 300)
    points[rows[:150], cols[:150]] = np.nan
    points[rows[150:], cols[150:]] = np.where(rng.uniform(size=150) < 0.5, np.inf, -np.inf)
    finite, mask = validate_cloud(points, "source", 32)
    truth = np.array([all(np.isfinite(row)) for row in points])
    np.testing.assert_array_equal(mask, truth)
    np.testing.assert_array_equal(finite, points[truth])
    clean = rng.normal(size=(1000, 3)).astype(np.float32)
    same, every = validate_cloud(clean, "source", 32)
    assert same is clean and every.all() and len(every) == 1000
    huge = np.full((100, 3), 3e38, dtype=np.float32)  # finite, but their sum overflows
    kept, mask = validate_cloud(huge, "source", 32)
    assert mask.all() and len(kept) == 100
    ints, mask = validate_cloud(np.arange(300).reshape(100, 3), "source", 32)
    assert mask.all() and ints.dtype.kind == "i"


@pytest.mark.parametrize("n", [1, 3, 5, 4097, 70_001])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32])
def test_aligned_rows_are_float32_and_equal_a_float64_reference(n, dtype):
    rng = np.random.default_rng(n)
    points = (rng.normal(size=(n, 3)) * 20 + [100, -50, 3]).astype(dtype)
    T = random_transform(rng, 90.0, 5.0)
    out = transform_rows(T, points)
    reference = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    assert out.dtype == np.float32 and out.shape == (n, 3)
    np.testing.assert_allclose(out, reference, rtol=0, atol=1e-5 * np.abs(reference).max())


def test_aligned_rows_of_strided_and_read_only_input():
    rng = np.random.default_rng(3)
    wide = rng.normal(size=(1001, 4)).astype(np.float32)
    wide[:, 3] = np.nan  # a padding field that must not leak in
    view = wide[:, :3]
    view.flags.writeable = False
    T = random_transform(rng, 30.0, 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = transform_rows(T, view)
    np.testing.assert_allclose(out, view.astype(np.float64) @ T[:3, :3].T + T[:3, 3], atol=1e-5)


def test_register_reports_aligned_finite_rows_in_input_order():
    rng = np.random.default_rng(4)
    src = (_surface(3000) * 10 + [5.0, 2.0, 1.0]).astype(np.float32)
    src[rng.integers(0, 3000, 200)] = np.nan
    T_true = random_transform(rng, 10.0, 0.5)
    tgt = apply_transform(T_true, np.nan_to_num(src, nan=0.0)).astype(np.float32)
    res = Registrar(GenRegNet(SMALL)).register(src, tgt)
    truth = np.isfinite(src).all(axis=1)
    np.testing.assert_array_equal(res.source_valid_mask, truth)
    reference = apply_transform(res.transformation, src[truth].astype(np.float64))
    assert res.aligned_source.dtype == np.float32
    np.testing.assert_allclose(res.aligned_source, reference, atol=1e-5 * np.abs(reference).max())


def test_fitness_and_rmse_equal_open3d_evaluate_registration():
    rng = np.random.default_rng(5)
    tgt = _surface(4000, seed=1)
    src = apply_transform(random_transform(rng, 5.0, 0.05), _surface(3000, seed=2))
    T = random_transform(rng, 3.0, 0.02)
    for threshold in (0.01, 0.05, 0.2):
        ev = o3d.pipelines.registration.evaluate_registration(
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)),
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt)), threshold, T)
        fitness, rmse = overlap_fitness(src, tgt, T, threshold)
        assert fitness == pytest.approx(ev.fitness, abs=1e-12) and rmse == pytest.approx(ev.inlier_rmse, rel=1e-9)
    assert overlap_fitness(src, tgt + 100.0, T, 0.01) == (0.0, 0.0)


def test_spacing_equals_scipy():
    cloud = _surface(2000, seed=3)
    distances, _ = cKDTree(cloud).query(cloud, k=2)
    assert point_spacing(cloud) == pytest.approx(float(np.median(distances[:, 1])), rel=1e-12)


def test_normals_equal_the_lapack_smallest_eigenvector():
    cloud = _surface(3000, seed=4)
    _, neighbours = cKDTree(cloud).query(cloud[:500], k=20)
    normals = plane_normals(cloud, neighbours)
    sets = cloud[neighbours]
    centred = sets - sets.mean(axis=1, keepdims=True)
    truth = np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))[1][:, :, 0]
    np.testing.assert_allclose(np.abs((normals * truth).sum(axis=1)), 1.0, atol=1e-9)
    assert np.allclose(plane_normals(np.zeros((5, 3)), np.zeros((2, 3), dtype=int)), 0.0)  # no spread: zero
    # about the cloud's mean given (a TargetIndex works it out once): the same normals, bit for bit
    np.testing.assert_array_equal(plane_normals(cloud, neighbours, kernels.cloud_mean(cloud)), normals)
    np.testing.assert_allclose(kernels.cloud_mean(cloud), cloud.mean(axis=0), rtol=1e-12)


def _reference_covariance(moved, target, origin, max_distance, inflation, floor):
    """The covariance formula of `pose_covariance` with scipy's tree and Open3D's KNN normals."""
    distances, index = cKDTree(target).query(moved, distance_upper_bound=max_distance)
    found = np.isfinite(distances)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    normals = np.asarray(cloud.normals)[index[found]]
    x = moved[found]
    r = np.einsum("ij,ij->i", normals, x - target[index[found]])
    J = np.concatenate([normals, np.cross(x - origin, normals)], axis=1)
    C = inflation * float(r @ r) / (len(r) - 6) * np.linalg.inv(J.T @ J) + np.diag([floor[0] ** 2] * 3 + [floor[1] ** 2] * 3)
    return 0.5 * (C + C.T)


def test_covariance_equals_the_reference_formula_and_the_normalised_frame_scales_to_metres():
    rng = np.random.default_rng(6)
    target = _surface(5000, seed=5) * 3.0
    moved = apply_transform(random_transform(rng, 1.0, 0.01), _surface(5000, seed=6) * 3.0)
    origin, distance, floor = np.array([0.3, -0.1, 0.2]), 0.05, (0.003, 0.002)
    truth = _reference_covariance(moved, target, origin, distance, 44.7, floor)
    full = pose_covariance(moved, target, origin, distance, 44.7, floor, max_rows=None)
    np.testing.assert_allclose(full, truth, rtol=1e-6)
    scale, offset = 2.5, np.array([1.0, 2.0, -1.0])  # the same clouds in a normalised frame
    C = pose_covariance((moved - offset) / scale, (target - offset) / scale, (origin - offset) / scale,
                        distance / scale, 44.7, floor, scale=scale, max_rows=None)
    np.testing.assert_allclose(C, truth, rtol=1e-6)
    # the default estimates the Hessian on 1000 of the ~5000 correspondences: standard deviations within 10 %
    sub = pose_covariance(moved, target, origin, distance, 44.7, (0.0, 0.0))
    ref = _reference_covariance(moved, target, origin, distance, 44.7, (0.0, 0.0))
    np.testing.assert_allclose(np.sqrt(np.diag(sub)), np.sqrt(np.diag(ref)), rtol=0.1)


def test_a_pair_indexes_its_target_once_and_the_index_answers_fresh_queries_afresh():
    cloud = _surface(500, seed=7)
    index = TargetIndex(cloud)
    assert TargetIndex.of(index) is index and TargetIndex.of(cloud) is not TargetIndex.of(cloud)
    query = cloud + 0.001
    first = index.nearest(query)
    query[0] += 10.0  # different points: answered afresh, not from memory
    moved = index.nearest(query)
    assert moved[1][0] > first[1][0] and np.array_equal(moved[0][1:], first[0][1:])


def test_point_to_plane_target_carries_open3d_knn_normals_and_refines_identically():
    """`PreparedPair.plane_target` (the target with `TargetIndex`'s normals, built once per pair) holds the
    normals Open3D's own KNN estimate gives (up to sign), and point-to-plane ICP on it returns the transform
    ICP on the bare array (normals estimated by Open3D) returns, to 1e-9."""
    from genreg_core.config import RefineConfig, RegistrationConfig
    from genreg_core.prepare import model_frame_config, prepare_pair
    from genreg_core.refine import estimate_normals, o3d_cloud, refine

    src = _surface(6000, seed=3)
    tgt = apply_transform(random_transform(np.random.default_rng(4), 10.0, 0.1), _surface(6000, seed=5))
    p = prepare_pair(src, tgt, None, num_points=256, refine_points=3000, min_points=16, seed=0)
    ours = np.asarray(p.plane_target.normals)
    theirs = np.asarray(estimate_normals(o3d_cloud(p.dense_tgt)).normals)
    assert np.percentile(np.abs(np.einsum("ij,ij->i", ours, theirs)), 1) > 1 - 1e-9
    cfg = model_frame_config(RegistrationConfig(refine=RefineConfig(method="point_to_plane")), p.scale).refine
    start = random_transform(np.random.default_rng(6), 3.0, 0.02)
    np.testing.assert_allclose(refine(p.dense_src, p.plane_target, start, cfg),
                               refine(p.dense_src, p.dense_tgt, start, cfg), atol=1e-9)


@pytest.mark.parametrize("fine_fraction", [1.0, 0.25])
def test_gicp_on_the_scores_index_searches_its_tree_and_refines_identically(fine_fraction):
    """GICP's target as `PreparedPair.target_index` (its k-d tree shared with the scores, its covariances
    prepared once for every candidate, both stages on one prepared source) gives bit for bit the transform
    GICP gives on the bare array, prepared afresh for each stage, and it recovers the known motion."""
    from genreg_core.config import RefineConfig, RegistrationConfig
    from genreg_core.prepare import model_frame_config, prepare_pair
    from genreg_core.refine import refine

    src = _surface(6000, seed=3)
    truth = random_transform(np.random.default_rng(4), 3.0, 0.02)
    p = prepare_pair(src, apply_transform(truth, _surface(6000, seed=5)), None, num_points=256, refine_points=3000,
                     min_points=16, seed=0)
    refine_cfg = RefineConfig(method="gicp", fine_fraction=fine_fraction)
    cfg = model_frame_config(RegistrationConfig(refine=refine_cfg), p.scale).refine
    shared, own = refine(p.dense_src, p.target_index, np.eye(4), cfg), refine(p.dense_src, p.dense_tgt, np.eye(4), cfg)
    assert np.array_equal(shared, own)
    prepared = p.target_index.gicp
    assert np.array_equal(refine(p.dense_src, p.target_index, np.eye(4), cfg), shared)
    assert p.target_index.gicp is prepared  # the second candidate reused the target's covariances
    re, te = transform_errors(p.to_input_units(shared), truth)
    assert re < 0.5 and te < 0.01


def test_gicp_prepares_on_more_threads_with_the_same_transform():
    """GICP's k-d trees and covariances of both clouds on two threads (`GICPTarget`'s threads; the alignment
    on one) give bit for bit the transform of a one-thread run, and it recovers the known motion."""
    from genreg_core.refine import GICPTarget
    from genreg_core.score import TargetIndex

    src = _surface(6000, seed=7)
    truth = random_transform(np.random.default_rng(8), 3.0, 0.02)
    tgt = apply_transform(truth, _surface(6000, seed=9))
    runs = [GICPTarget(TargetIndex(tgt, threads=n), threads=n).align(
        src, max_distance=0.3, max_iterations=20, fine=(0.075, 10)) for n in (1, 2)]
    assert np.array_equal(runs[0], runs[1])
    re, te = transform_errors(runs[0], truth)
    assert re < 0.5 and te < 0.01
