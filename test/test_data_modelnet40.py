"""ModelNet40 reader and the paper's pair protocol, checked against independent truth (real data)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from genreg_core.config import data_root
from genreg_core.data import ModelNetPairs, ModelNetShapes, balanced_sampler_indices, load_modelnet40
from genreg_core.errors import ConfigError, DataNotFoundError

pytestmark = pytest.mark.skipif(
    not (data_root() / "modelnet40").is_dir(), reason="ModelNet40 data not available"
)


@pytest.fixture(scope="module")
def test_seen() -> ModelNetShapes:
    return load_modelnet40("test", "seen")


@pytest.fixture(scope="module")
def small(test_seen: ModelNetShapes) -> ModelNetShapes:
    """40 seen test shapes, two of each of the 20 categories."""
    idx = np.concatenate([np.flatnonzero(test_seen.labels == c)[:2] for c in range(20)])
    return ModelNetShapes(
        test_seen.points[idx], test_seen.labels[idx], test_seen.names[idx], test_seen.class_names
    )


def unit_box(points: np.ndarray) -> np.ndarray:
    """Independent re-implementation: min corner to 0, longest side to 1."""
    p = points.astype(np.float64)
    lo = p.min(axis=0)
    return (p - lo) / (p.max(axis=0) - lo).max()


def to_object_frame(item: dict) -> tuple[np.ndarray, np.ndarray]:
    T = item["transform"].astype(np.float64)
    R, t = T[:3, :3], T[:3, 3]
    return item["source"].astype(np.float64), (item["target"] - t) @ R  # R^T (y - t), rows


def test_split_counts_and_categories(test_seen: ModelNetShapes) -> None:
    unseen = load_modelnet40("test", "unseen")
    every = load_modelnet40("test", "all")
    assert (len(test_seen), len(unseen), len(every)) == (1202, 1266, 2468)
    assert test_seen.labels.max() == 19 and unseen.labels.min() == 20
    assert test_seen.points.shape == (1202, 1024, 3) and test_seen.points.dtype == np.float32
    assert test_seen.labels.dtype == np.int64
    names = (data_root() / "modelnet40" / "modelnet40_shape_names.txt").read_text().split()
    assert test_seen.class_names == tuple(names) and len(names) == 40
    # Shape ids carry their category name, so labels index the right class.
    for lab, name in zip(unseen.labels[::97], unseen.names[::97], strict=True):
        assert name.rsplit("_", 1)[0] == names[lab]
    assert int((test_seen.labels == names.index("desk")).sum()) == 86
    # Unit sphere, as the README says.
    norms = np.linalg.norm(test_seen.points[:50], axis=-1).max(axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=2e-3)


def test_train_split_is_seen_only() -> None:
    train = load_modelnet40("train", "seen")
    assert len(train) == 5114 and set(np.unique(train.labels)) == set(range(20))
    for bad in ("unseen", "all"):
        with pytest.raises(ConfigError, match="seen"):
            load_modelnet40("train", bad)
    with pytest.raises(ConfigError):
        load_modelnet40("val", "seen")
    with pytest.raises(ConfigError):
        load_modelnet40("test", "novel")


def test_data_root_override_and_missing(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("GENREG_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(DataNotFoundError):
        load_modelnet40("test", "seen")
    folder = tmp_path / "fake" / "modelnet40"
    folder.mkdir(parents=True)
    names = [f"c{k}" for k in range(40)]
    (folder / "modelnet40_shape_names.txt").write_text("\n".join(names) + "\n")
    pts = np.random.default_rng(0).normal(size=(3, 1024, 3)).astype(np.float16)
    np.savez(folder / "test.npz", points=pts, labels=np.array([1, 25, 3]), names=np.array(["a", "b", "c"]))
    monkeypatch.setenv("GENREG_DATA", str(tmp_path / "fake"))
    shapes = load_modelnet40("test", "seen", root="/definitely/not/here")  # env wins over the setting
    assert list(shapes.labels) == [1, 3] and list(shapes.names) == ["a", "c"]
    np.testing.assert_array_equal(shapes.points, pts[[0, 2]].astype(np.float32))
    with pytest.raises(DataNotFoundError):  # train.npz missing
        load_modelnet40("train", "seen")


def test_clean_protocol_statistics(small: ModelNetShapes) -> None:
    ds = ModelNetPairs(small, num_points=512, variant="clean")
    angles, shifts = [], []
    for i in range(len(ds)):
        item = ds[i]
        assert item["source"].shape == (512, 3) and item["target"].shape == (512, 3)
        assert item["source"].dtype == np.float32 and item["transform"].shape == (4, 4)
        assert item["label"] == small.labels[i] and item["variant"] == "clean"
        T = item["transform"].astype(np.float64)
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
        assert np.linalg.det(R) > 0.99
        angles.append(np.degrees(Rotation.from_matrix(R).magnitude()))
        shifts.append(np.linalg.norm(T[:3, 3]))
        # Both clouds are draws of the shape's unit-box-normalised points.
        shape = unit_box(small.points[i])
        src, tgt_obj = to_object_frame(item)
        assert src.min() >= -1e-6 and src.max() <= 1 + 1e-6
        tree = cKDTree(shape)
        d_src, i_src = tree.query(src)
        d_tgt, i_tgt = tree.query(tgt_obj)
        assert d_src.max() < 1e-5 and d_tgt.max() < 1e-4
        # Subsets without repetition, drawn independently (about half of the points shared).
        assert len(np.unique(i_src)) >= 505 and len(np.unique(i_tgt)) >= 505
        shared = len(np.intersect1d(i_src, i_tgt))
        assert 180 < shared < 340
    angles, shifts = np.array(angles), np.array(shifts)
    assert angles.max() <= 45.0 + 1e-3 and shifts.max() <= 0.8 + 1e-6
    assert angles.max() > 30.0 and shifts.max() > 0.5  # the range is actually used
    assert 12.0 < angles.mean() < 33.0


def test_full_resolution_is_two_permutations(small: ModelNetShapes) -> None:
    ds = ModelNetPairs(small, num_points=1024)
    item = ds[3]
    src, tgt_obj = to_object_frame(item)
    shape = unit_box(small.points[3])
    _, i_src = cKDTree(shape).query(src)
    _, i_tgt = cKDTree(shape).query(tgt_obj)
    np.testing.assert_allclose(np.sort(src, axis=0), np.sort(shape, axis=0), atol=1e-6)
    np.testing.assert_allclose(np.sort(tgt_obj, axis=0), np.sort(shape, axis=0), atol=1e-4)
    assert (i_src != i_tgt).mean() > 0.9  # independent orders


def test_partial_drops_the_largest_x(small: ModelNetShapes) -> None:
    ds = ModelNetPairs(small, num_points=512, variant="partial", partial_ratio=0.2)
    for i in range(0, len(ds), 7):
        item = ds[i]
        assert item["variant"] == "partial"
        shape = unit_box(small.points[i])
        largest = np.argsort(shape[:, 0])[-205:]  # round(0.2 * 1024) points with the largest x
        src, tgt_obj = to_object_frame(item)
        d, i_tgt = cKDTree(shape).query(tgt_obj)
        assert d.max() < 1e-4
        cut = shape[largest, 0].min()
        assert tgt_obj[:, 0].max() <= cut + 1e-4  # nothing beyond the crop plane
        beyond = np.flatnonzero(shape[:, 0] > cut + 1e-6)
        assert len(np.intersect1d(i_tgt, beyond)) == 0  # ties exactly at the cut may survive
        assert src[:, 0].max() > cut  # the source keeps the whole shape
    # Over many epochs the target draws cover everything below the crop plane: only 20 % is dropped.
    shape = unit_box(small.points[0])
    cut = np.sort(shape[:, 0])[-205]
    seen = set()
    for epoch in range(12):
        ds.set_epoch(epoch)
        seen |= set(cKDTree(shape).query(to_object_frame(ds[0])[1])[1].tolist())
    below = set(np.flatnonzero(shape[:, 0] < cut - 1e-6).tolist())
    assert len(below - seen) <= 0.01 * len(below)


def test_noise_has_requested_sigma_on_target_only(small: ModelNetShapes) -> None:
    clean = ModelNetPairs(small, variant="clean", seed=4)
    noisy = ModelNetPairs(small, variant="noise", noise_sigma=0.02, seed=4)
    diffs = []
    for i in range(0, len(small), 4):
        a, b = clean[i], noisy[i]
        np.testing.assert_array_equal(a["source"], b["source"])
        np.testing.assert_array_equal(a["transform"], b["transform"])
        diffs.append(b["target"] - a["target"])
    diffs = np.concatenate(diffs).ravel()
    assert abs(diffs.std() - 0.02) < 0.001 and abs(diffs.mean()) < 0.001
    # Independent of the clean twin: residual to the true surface point grows by the noise.
    item = noisy[0]
    _, tgt_obj = to_object_frame(item)
    d, _ = cKDTree(unit_box(small.points[0])).query(tgt_obj)
    assert np.median(d) > 0.01


def test_mixed_variants_and_curriculum(small: ModelNetShapes) -> None:
    ds = ModelNetPairs(small, variant=("clean", "noise", "partial"), max_angle_deg=45.0)
    kinds = [ds[i]["variant"] for i in range(len(ds))]
    assert set(kinds) == {"clean", "noise", "partial"}
    for i, kind in enumerate(kinds[:12]):
        _, tgt_obj = to_object_frame(ds[i])
        d, _ = cKDTree(unit_box(small.points[i])).query(tgt_obj)
        assert (np.median(d) > 3e-3) == (kind == "noise")
    ds.max_angle_deg = 5.0
    angles = [np.degrees(Rotation.from_matrix(ds[i]["transform"][:3, :3]).magnitude()) for i in range(20)]
    assert max(angles) <= 5.0 + 1e-3


def test_determinism_and_epochs(small: ModelNetShapes) -> None:
    a = ModelNetPairs(small, variant=("clean", "noise"), seed=1)
    b = ModelNetPairs(small, variant=("clean", "noise"), seed=1)
    c = ModelNetPairs(small, variant=("clean", "noise"), seed=2)
    first = [a[i] for i in range(5)]
    for i in range(5):
        for key in ("source", "target", "transform"):
            np.testing.assert_array_equal(first[i][key], b[i][key])
        assert not np.allclose(first[i]["transform"], c[i]["transform"])
    a.set_epoch(1)
    assert all(not np.allclose(first[i]["source"], a[i]["source"]) for i in range(5))
    a.set_epoch(0)
    np.testing.assert_array_equal(a[4]["target"], first[4]["target"])
    assert not np.allclose(a[0]["transform"], a[1]["transform"])
    np.testing.assert_array_equal(a[-1]["source"], a[len(a) - 1]["source"])
    with pytest.raises(IndexError):
        a[len(a)]


def test_argument_checks(small: ModelNetShapes) -> None:
    with pytest.raises(ConfigError):
        ModelNetPairs(small, variant="blurry")
    with pytest.raises(ConfigError):
        ModelNetPairs(small, num_points=2048)
    with pytest.raises(ConfigError):  # 1024 points cannot all survive a 20 % crop
        ModelNetPairs(small, num_points=1024, variant="partial")
    ModelNetPairs(small, num_points=1024, variant="noise")


def test_dataloader_batches(small: ModelNetShapes) -> None:
    loader = torch.utils.data.DataLoader(ModelNetPairs(small, num_points=256), batch_size=8)
    batch = next(iter(loader))
    assert batch["source"].shape == (8, 256, 3) and batch["transform"].shape == (8, 4, 4)
    assert batch["source"].dtype == torch.float32 and batch["label"].shape == (8,)


def test_balanced_sampler() -> None:
    labels = np.array([0] * 90 + [1] * 9 + [5] * 1)
    rng = np.random.default_rng(0)
    idx = balanced_sampler_indices(labels, 301, rng)
    assert idx.dtype == np.int64 and len(idx) == 301 and idx.min() >= 0 and idx.max() < 100
    counts = np.bincount(labels[idx], minlength=6)[[0, 1, 5]]
    assert counts.max() - counts.min() <= 1 and counts.sum() == 301
    assert len(np.unique(idx[labels[idx] == 0])) > 40  # draws spread within a class
    assert not np.all(np.diff(idx) >= 0)  # shuffled
