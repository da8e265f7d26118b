"""genreg_core.preprocess: range filter, crop box and voxel grid, checked against brute-force truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from genreg_core.errors import ConfigError
from genreg_core.preprocess import (
    PreprocessConfig,
    crop_mask,
    preprocess,
    range_mask,
    voxel_downsample,
    voxel_downsample_reference,
)


def test_range_mask_and_nonfinite():
    p = np.array([[0.5, 0, 0], [0, 2, 0], [3, 4, 0], [np.nan, 0, 0], [0, 0, np.inf]])
    np.testing.assert_array_equal(range_mask(p, 1.0, 4.0), [False, True, False, False, False])
    np.testing.assert_array_equal(range_mask(p), [True, True, True, False, False])


def test_crop_box_is_closed():
    p = np.array([[0, 0, 0], [1, 1, 1], [1.0001, 0, 0], [-0.5, 0.5, 0.5]])
    np.testing.assert_array_equal(crop_mask(p, [0, 0, 0], [1, 1, 1]), [True, True, False, False])


def test_voxel_centroids_match_brute_force():
    rng = np.random.default_rng(0)
    p = rng.uniform(-2, 3, (5000, 3))
    out = voxel_downsample(p, 0.5)
    keys = np.floor(p / 0.5).astype(int)
    truth = {}
    for k, x in zip(map(tuple, keys), p):
        truth.setdefault(k, []).append(x)
    assert len(out) == len(truth)
    expected = np.array([np.mean(v, axis=0) for v in truth.values()])  # dict keeps first-appearance order
    np.testing.assert_allclose(out, expected, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 3000), spread=st.sampled_from([0.01, 1.0, 40.0, 1e5]),
       voxel=st.sampled_from([1e-3, 0.02, 0.2, 1.0]), repeats=st.integers(0, 5), float32=st.booleans())
def test_the_compiled_voxel_grid_is_the_sorting_one_bit_for_bit(seed, n, spread, voxel, repeats, float32):
    """`voxel_downsample` (the hash-table kernel) equals `voxel_downsample_reference` (sorted keys) exactly, in
    values, order and dtype: clouds dense and sparse in their voxels, far from the origin, with repeated rows
    and points on voxel faces, float32 and float64."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3)) * spread + rng.uniform(-1e3, 1e3, 3)
    face = rng.random(n) < 0.1  # on voxel faces
    points[face] = np.round(points[face] / voxel) * voxel
    points = np.concatenate([points] + [points[rng.permutation(n)[: n // 3]]] * repeats)
    points = points.astype(np.float32 if float32 else np.float64)
    ours, reference = voxel_downsample(points, voxel), voxel_downsample_reference(points, voxel)
    assert ours.dtype == reference.dtype == points.dtype
    assert ours.shape == reference.shape
    assert np.array_equal(ours, reference)


def test_non_finite_points_take_the_reference_voxel_grid():
    p = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [np.nan, 0, 0], [2.0, 2.0, 2.0]])
    assert np.array_equal(voxel_downsample(p, 1.0), voxel_downsample_reference(p, 1.0), equal_nan=True)
    np.testing.assert_allclose(voxel_downsample(p[[0, 1, 3]], 1.0), [[0.15, 0.15, 0.15], [2.0, 2.0, 2.0]])


def test_preprocess_chain_and_noop():
    p = np.array([[0.1, 0, 0], [1, 1, 1], [1.05, 1.05, 1.0], [5, 5, 5], [np.nan, 1, 1]])
    cfg = PreprocessConfig(min_range=0.5, max_range=5.0, crop_min=(0, 0, 0), crop_max=(2, 2, 2), voxel_size=0.5)
    np.testing.assert_allclose(preprocess(p, cfg), [[1.025, 1.025, 1.0]])
    assert preprocess(p, PreprocessConfig()) is p


@pytest.mark.parametrize(
    "kwargs",
    [{"min_range": 2.0, "max_range": 1.0}, {"voxel_size": -1.0}, {"crop_min": (0, 0, 0)},
     {"crop_min": (0, 0, 0), "crop_max": (1, -1, 1)}],
)
def test_bad_configs(kwargs):
    with pytest.raises(ConfigError):
        PreprocessConfig(**kwargs)
