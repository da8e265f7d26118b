"""Real sensors' quirks through the registration API: repeated points (a LiDAR's dual returns), clouds of
one point, lines and planes, float32 clouds far from the origin, unusable checkpoints. The truth is a
known transform, numpy's `unique`, or the geometry itself (a line's direction, a plane's normal)."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from genreg_core.checkpoint import load_checkpoint
from genreg_core.config import SCENE_PDSAC, RefineConfig, RegistrationConfig
from genreg_core.data import RGBDSequence, load_modelnet40
from genreg_core.errors import CheckpointError, InvalidPointCloudError, TooFewPointsError
from genreg_core.geometry import apply_transform, make_transform
from genreg_core.metrics import transform_errors
from genreg_core.model.invariant import invariant_geometry
from genreg_core.registration import Registrar

SHIPPED = ("modelnet40", "modelnet40_dgcnn", "modelnet40_partial", "7scenes")
WARN_CONFIDENCE = 0.3  # the node's default warn_confidence (genreg_ros.config)


@pytest.fixture(scope="module")
def registrars() -> dict[str, Registrar]:
    scene = RegistrationConfig(pdsac=SCENE_PDSAC, refine=RefineConfig(method="gicp"))
    return {name: Registrar.from_checkpoint(name, scene if name == "7scenes" else None) for name in SHIPPED}


@pytest.fixture(scope="module")
def shape() -> np.ndarray:
    """One held-out ModelNet40 shape (unseen category, 1024 points, unit sphere)."""
    return load_modelnet40("test", "unseen").points[7].astype(np.float32)


def with_repeats(points: np.ndarray, rng: np.random.Generator, share: float = 0.05, cluster: int = 40) -> np.ndarray:
    """`points` plus `share` of them again (dual returns) and one point repeated `cluster` times (more than
    the encoder's k: a neighbourhood with no spread)."""
    again = points[rng.choice(len(points), int(share * len(points)), replace=False)]
    return rng.permutation(np.concatenate([points, again, np.repeat(points[:1], cluster, axis=0)]))


def test_repeated_rows_agrees_with_numpy_unique():
    from genreg_core.prepare import repeated_rows

    rng = np.random.default_rng(3)
    x = rng.standard_normal((3000, 3))
    assert not repeated_rows(x).any() and not repeated_rows(x[:1]).any()  # distinct rows: no hash repeats either
    x = np.concatenate([x, x[rng.choice(3000, 400)], [[0.0, -0.0, 1.0], [-0.0, 0.0, 1.0]]])
    repeated = repeated_rows(x)
    assert (~repeated).sum() == len(np.unique(x + 0.0, axis=0))  # numpy: -0.0 == 0.0 after + 0.0
    assert len(np.unique(x[~repeated], axis=0)) == (~repeated).sum()  # what is kept is distinct


def test_distinct_subsample_is_subsample_when_nothing_repeats_and_distinct_otherwise():
    from genreg_core.prepare import distinct_subsample, subsample

    rng_points = np.random.default_rng(4)
    x = rng_points.standard_normal((20000, 3)).astype(np.float32)
    for n, ordered in ((512, False), (5000, True)):
        assert np.array_equal(distinct_subsample(x, n, np.random.default_rng(0), ordered),
                              subsample(x, n, np.random.default_rng(0), ordered))  # shipped outputs unchanged
    dual = np.concatenate([x, x[:2000]])
    rows = distinct_subsample(dual, 5000, np.random.default_rng(0), ordered=True)
    assert len(rows) == 5000 and len(np.unique(rows, axis=0)) == 5000
    few = np.repeat(x[:10], 100, axis=0)  # 10 distinct points
    assert len(np.unique(distinct_subsample(few, 512, np.random.default_rng(0)), axis=0)) == 10
    assert len(distinct_subsample(few, 5000, np.random.default_rng(0), ordered=True, repeat=False)) == 10


def test_spread_free_neighbourhoods_give_finite_features_in_both_paths():
    """A point repeated more than k times has a neighbourhood without spread: zero normal, finite features
    (they were NaN, and the row maximum then indexed past the end)."""
    rng = np.random.default_rng(5)
    x = rng.standard_normal((1, 256, 3)).astype(np.float32)
    x[0, :40] = x[0, 0]
    points = torch.from_numpy(x)
    from genreg_core.model.gcnn import knn_indices
    neighbours = knn_indices(points, 20)
    compiled = invariant_geometry(points, neighbours)
    with torch.no_grad():
        from genreg_core.model.invariant import local_shape, point_pair_features
        from genreg_core.model.layers import gather_neighbours
        normals, evals = local_shape(points, neighbours)
        edge = point_pair_features(points, normals, gather_neighbours(points, neighbours),
                                   gather_neighbours(normals, neighbours))
    for result in (*compiled, normals, evals, edge):
        assert torch.isfinite(result).all()
    assert torch.count_nonzero(compiled[2][0, :40]) == 0  # the inference path: no direction at all


@pytest.mark.parametrize("name", SHIPPED)
def test_repeated_points_register_with_every_shipped_model(name, registrars, shape):
    """5 % dual returns and one point repeated as often: every shipped model registers (they raised
    RuntimeError)."""
    rng = np.random.default_rng(6)
    T = make_transform(Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([0.1, -0.05, 0.02]))
    if name == "7scenes":
        seq = RGBDSequence.redkitchen()
        source, target = seq.points(850)[::8], seq.points(850)[::8]  # one validation frame, moved
    else:
        source, target = shape, shape
    cluster = len(source) // 20  # as many copies of one point as a driver's no-return rows (0, 0, 0)
    source = with_repeats(source.astype(np.float32), rng, cluster=cluster)
    target = with_repeats(target.astype(np.float32), rng, cluster=cluster)
    result = registrars[name].register(source, apply_transform(T, target))
    rotation_error, translation_error = transform_errors(result.transformation, T)
    assert np.isfinite(result.transformation).all() and np.isfinite(result.confidence)
    assert rotation_error < 2.0 and translation_error < 0.02


def test_a_cloud_of_one_repeated_point_is_too_few_points(registrars, shape):
    with pytest.raises(TooFewPointsError, match="1 distinct"):
        registrars["modelnet40_dgcnn"].register(np.repeat(shape[:1], 1000, axis=0), shape)
    with pytest.raises(TooFewPointsError, match="target has 5 distinct"):
        registrars["7scenes"].register(shape, np.repeat(shape[:5], 200, axis=0))


def test_lines_and_planes_report_their_unconstrained_motions_with_low_confidence(registrars):
    rng = np.random.default_rng(8)
    direction = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
    line = (rng.random((3000, 1)) * direction + 0.002 * rng.standard_normal((3000, 3))).astype(np.float32)
    plane = np.c_[rng.random((3000, 2)) * 2, 0.002 * rng.standard_normal(3000)].astype(np.float32)
    for name in ("modelnet40_dgcnn", "7scenes"):
        for cloud, axis in ((line, direction), (plane, np.array([0.0, 0.0, 1.0]))):
            result = registrars[name].register(cloud, cloud)
            assert result.degenerate and result.confidence < WARN_CONFIDENCE
            rotations = [np.array(text[text.index("(") + 1:-1].split(", "), dtype=float)
                         for text in result.unconstrained if text.startswith("rotation about")]
            assert any(abs(u @ axis) > 0.95 for u in rotations), result.unconstrained  # about the line / normal
    seq = RGBDSequence.redkitchen()
    room = registrars["7scenes"].register(seq.points(820)[::4], seq.points(830)[::4])
    assert not room.degenerate and room.unconstrained == ()


def test_float32_clouds_far_from_the_origin_score_as_at_the_origin(registrars):
    """At 1e6 m float32 holds 1/16 m steps: a cloud on that grid is the same cloud at the origin and there.
    Its repeated points made the target spacing 0, and so fitness and confidence 0."""
    seq = RGBDSequence.redkitchen()
    grid = 1.0 / 16.0

    def on_grid(points: np.ndarray) -> np.ndarray:
        return np.round(points / grid) * grid  # float32's steps at 1e6 m: many points fall together

    source, target = on_grid(seq.points(900)[::4]), on_grid(seq.points(910)[::4])
    T_true = np.linalg.inv(seq.pose(910)) @ seq.pose(900)
    reg = registrars["7scenes"]
    near = reg.register(source.astype(np.float32), target.astype(np.float32))
    offset = np.array([1e6, -1e6, 30.0])
    far = reg.register((source + offset).astype(np.float32), (target + offset).astype(np.float32))
    assert np.array_equal((source + offset).astype(np.float32) - offset, source)  # exact: the same cloud
    assert far.fitness > 0.5 and abs(far.fitness - near.fitness) < 0.05
    assert abs(far.confidence - near.confidence) < 0.05
    T_far = make_transform(np.eye(3), -offset) @ far.transformation @ make_transform(np.eye(3), offset)
    for T in (near.transformation, T_far):
        rotation_error, translation_error = transform_errors(T, T_true)
        assert rotation_error < 2.0 and translation_error < 0.1  # the grid's steps are 6 cm


def test_coordinates_beyond_float_range_are_invalid(registrars, shape):
    reg = registrars["modelnet40_dgcnn"]
    with pytest.raises(InvalidPointCloudError, match="too large"):
        reg.register(shape.astype(np.float64) * 1.5e308, shape)  # extent overflows
    for factor in (1e300, 1e20, 1e7):  # beyond float32, beyond its squares, a million extents away
        with pytest.raises(InvalidPointCloudError, match="source extents"):
            reg.register(shape, shape.astype(np.float64) * factor)
    outlier = np.concatenate([np.repeat(shape, 2, axis=0), [[1e25, 0.0, 0.0]]])  # one stray point, robust extent
    with pytest.raises(InvalidPointCloudError, match="source extents"):
        reg.register(outlier, shape)
    reg.register(shape, shape.astype(np.float64) * 1e4)  # a scan in a map 10,000x its size still runs
    # a target 1e-33 source extents wide (distinct points, but a point at the source's scale: its squared
    # distances leave float32, and the network's outputs were NaN), and a source as small beside its target
    for source, target in ((shape * 1e11, shape * 1e-22), (shape * 1e-22, shape)):
        with pytest.raises(InvalidPointCloudError, match="same units"):
            reg.register(source.astype(np.float64), target.astype(np.float64))
    reg.register(shape, shape.astype(np.float64) * 1e-4)  # a target 10,000x smaller than the scan still runs


def test_the_row_maximum_of_a_row_holding_nan_is_torchs():
    """The compiled first index of a row's maximum has no maximum to find in a row holding NaN (NaN equals
    nothing): the row's value and index are torch's own (a valid index, not one past the end)."""
    from genreg_core.model.genreg import row_max

    x = torch.from_numpy(np.random.default_rng(3).standard_normal((1, 4, 6)).astype(np.float32))
    x[0, 2, 3] = float("nan")
    with torch.no_grad():
        top, index = row_max(x)
    want_top, want_index = x.max(dim=-1)
    assert torch.equal(index, want_index) and int(index.max()) < x.shape[-1]
    np.testing.assert_array_equal(top.numpy(), want_top.numpy())  # NaN where torch's is NaN


def test_unusable_checkpoints_say_why_in_one_line(tmp_path):
    shipped = load_checkpoint.__globals__["resolve_checkpoint"]("7scenes").read_bytes()
    (tmp_path / "truncated.pt").write_bytes(shipped[:20000])
    (tmp_path / "empty.pt").write_bytes(b"")
    (tmp_path / "folder.pt").mkdir()

    class RunsCode:
        def __reduce__(self):
            return os.getpid, ()

    (tmp_path / "code.pt").write_bytes(b"")
    torch.save({"x": RunsCode()}, tmp_path / "code.pt", pickle_protocol=pickle.HIGHEST_PROTOCOL)
    expected = {"truncated.pt": "is truncated or not a torch checkpoint", "empty.pt": "is empty (0 bytes)",
                "folder.pt": "is a directory", "code.pt": "refused, since loading them could run code"}
    for name, text in expected.items():
        with pytest.raises(CheckpointError) as caught:
            load_checkpoint(tmp_path / name)
        message = str(caught.value)
        assert text in message and "\n" not in message and "weights_only" not in message
