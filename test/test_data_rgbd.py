"""RGB-D readers (7-Scenes, SUN3D): depth decoding, intrinsics, back-projection, pose direction, pairs."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from genreg_core.config import data_root
from genreg_core.data import (
    FMRPairs,
    FramePairs,
    RGBDSequence,
    depth_to_points,
    read_depth,
    read_intrinsics,
    read_pose,
)
from genreg_core.errors import ConfigError, DataNotFoundError

ROOT = data_root()
needs_data = pytest.mark.skipif(not (ROOT / "7scenes").is_dir(), reason="RGB-D data not available")


def move(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


@pytest.fixture(scope="module")
def kitchen() -> RGBDSequence:
    return RGBDSequence.redkitchen()


def write_png16(path, values: np.ndarray) -> None:
    Image.fromarray(values.astype(np.uint16)).save(path)


def test_read_depth_invalid_values(tmp_path) -> None:
    raw = np.full((4, 5), 1234, dtype=np.uint16)
    raw[0, 0], raw[1, 2], raw[3, 4] = 0, 65535, 65534
    write_png16(tmp_path / "d.png", raw)
    depth = read_depth(tmp_path / "d.png")
    assert depth.dtype == np.float32 and depth.shape == (4, 5)
    assert np.isnan(depth[0, 0]) and np.isnan(depth[1, 2]) and np.isnan(depth).sum() == 2
    assert depth[2, 2] == pytest.approx(1.234) and depth[3, 4] == pytest.approx(65.534)
    K = np.array([[10.0, 0, 2], [0, 10.0, 1.5], [0, 0, 1]])
    assert len(depth_to_points(depth, K)) == 18
    with pytest.raises(DataNotFoundError):
        read_depth(tmp_path / "missing.png")


@needs_data
def test_read_depth_real_frame_with_65535() -> None:
    path = ROOT / "7scenes/stairs/seq-02/frame-000000.depth.png"
    raw = np.asarray(Image.open(path)).astype(np.int64)
    assert (raw == 65535).sum() > 1000  # this frame really carries both invalid markers
    depth = read_depth(path)
    invalid = (raw == 0) | (raw == 65535)
    np.testing.assert_array_equal(np.isnan(depth), invalid)
    np.testing.assert_allclose(depth[~invalid], raw[~invalid] / 1000.0, rtol=1e-6)
    seq = RGBDSequence.stairs(2)
    pts = seq.points(0)
    assert len(pts) == (~invalid).sum() and pts[:, 2].max() < 10.0 and pts[:, 2].min() > 0.3


@needs_data
def test_intrinsics_of_all_datasets(tmp_path) -> None:
    K7 = np.array([[585.0, 0, 320], [0, 585.0, 240], [0, 0, 1]])
    Ks = np.array([[570.342205, 0, 320], [0, 570.342205, 240], [0, 0, 1]])
    np.testing.assert_allclose(read_intrinsics(ROOT / "7scenes/redkitchen/camera-intrinsics.txt"), K7)
    np.testing.assert_allclose(read_intrinsics(ROOT / "sun3d/camera-intrinsics.txt"), Ks)  # tab separated
    np.testing.assert_allclose(RGBDSequence.redkitchen().K, K7)
    np.testing.assert_allclose(RGBDSequence.sun3d(2).K, Ks)
    for k in range(1, 5):
        np.testing.assert_allclose(RGBDSequence.stairs(k).K, K7)  # no file: 7-Scenes defaults
    (tmp_path / "k.txt").write_text("1 2\n3 4\n")
    with pytest.raises(DataNotFoundError):
        read_intrinsics(tmp_path / "k.txt")


def test_depth_to_points_geometry() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, size=(48, 64)).astype(np.float32)
    depth[5, 7] = np.nan
    depth[6, 8] = 0.0
    K = np.array([[60.0, 0, 31.5], [0, 55.0, 24.0], [0, 0, 1]])
    pts, pix = depth_to_points(depth, K, return_pixels=True)
    assert pts.dtype == np.float32 and len(pts) == 48 * 64 - 2 and pix.shape == (len(pts), 2)
    u, v = pix[:, 0], pix[:, 1]
    z = depth[v, u]
    np.testing.assert_allclose(pts[:, 2], z)
    np.testing.assert_allclose(pts[:, 0], (u - 31.5) * z / 60.0, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(pts[:, 1], (v - 24.0) * z / 55.0, rtol=1e-5, atol=1e-6)
    # A pixel right of and below the principal point lands at +x, +y (optical frame).
    i = np.flatnonzero((u == 50) & (v == 40))[0]
    assert pts[i, 0] > 0 and pts[i, 1] > 0
    pts2, pix2 = depth_to_points(depth, K, stride=4, min_depth=1.0, max_depth=3.0, return_pixels=True)
    assert np.all(pix2 % 4 == 0) and pts2[:, 2].min() >= 1.0 and pts2[:, 2].max() <= 3.0
    expected = depth[::4, ::4]
    assert len(pts2) == ((expected >= 1.0) & (expected <= 3.0)).sum()
    with pytest.raises(ConfigError):
        depth_to_points(depth, K, stride=0)


@needs_data
def test_sequences_on_disk(kitchen: RGBDSequence) -> None:
    assert kitchen.frame_indices == tuple(range(1000))
    assert RGBDSequence.sun3d(1).frame_indices == tuple(range(935, 985))
    assert RGBDSequence.sun3d(2).frame_indices == tuple(range(3160, 3210))
    for k in range(1, 5):
        assert RGBDSequence.stairs(k).frame_indices == (0, 1, 2)
    T = kitchen.pose(7)
    raw = np.loadtxt(ROOT / "7scenes/redkitchen/seq-01/frame-000007.pose.txt")
    np.testing.assert_allclose(T, raw, atol=1e-3)
    np.testing.assert_allclose(T[:3, 3], raw[:3, 3])  # translation untouched (metres)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    with pytest.raises(DataNotFoundError):
        kitchen.pose(1000)
    with pytest.raises(DataNotFoundError):
        RGBDSequence.sun3d(1).points(0)


@needs_data
def test_colors_follow_the_points(kitchen: RGBDSequence) -> None:
    pts = kitchen.points(0, stride=4)
    cols = kitchen.colors(0, stride=4)
    assert cols is not None and cols.shape == pts.shape and cols.dtype == np.uint8
    rgb = np.asarray(Image.open(ROOT / "7scenes/redkitchen/seq-01/frame-000000.color.jpg").convert("RGB"))
    _, pix = depth_to_points(kitchen.depth(0), kitchen.K, stride=4, return_pixels=True)
    np.testing.assert_array_equal(cols, rgb[pix[:, 1], pix[:, 0]])
    assert kitchen.colors(300) is None  # no colour for frames 200-799
    assert RGBDSequence.sun3d(1).colors(935) is None


@needs_data
def test_relative_pose_direction(kitchen: RGBDSequence) -> None:
    def median_gap(i: int, j: int, T: np.ndarray) -> float:
        tree = cKDTree(kitchen.points(j))
        return float(np.median(tree.query(move(T, kitchen.points(i, stride=4)))[0]))

    assert median_gap(100, 101, kitchen.relative_pose(100, 101)) < 0.005  # a few mm at gap 1
    good = median_gap(100, 110, kitchen.relative_pose(100, 110))
    wrong = median_gap(100, 110, kitchen.relative_pose(110, 100))  # the inverse direction
    still = median_gap(100, 110, np.eye(4))
    assert good < 0.01 and wrong > 0.05 and still > 0.03
    T_wi, T_wj = kitchen.pose(100), kitchen.pose(110)
    np.testing.assert_allclose(kitchen.relative_pose(100, 110), np.linalg.inv(T_wj) @ T_wi, atol=1e-9)


@needs_data
def test_frame_pairs(kitchen: RGBDSequence) -> None:
    pairs = FramePairs(kitchen, gap=5, frames=range(790, 800))
    assert len(pairs) == 5  # (790, 795) ... (794, 799): no frame of the validation part
    item = pairs[4]
    assert (item["target_index"], item["source_index"]) == (794, 799)
    np.testing.assert_allclose(item["transform"], kitchen.relative_pose(799, 794), atol=1e-6)
    np.testing.assert_array_equal(item["source"], kitchen.points(799))

    sub = FramePairs(kitchen, gap=1, frames=range(100, 103), num_points=300, seed=3, stride=4)
    a = sub[0]
    assert a["source"].shape == (300, 3) and a["target"].shape == (300, 3)
    assert cKDTree(kitchen.points(101, stride=4)).query(a["source"])[0].max() == 0.0
    assert cKDTree(kitchen.points(100, stride=4)).query(a["target"])[0].max() == 0.0
    assert len(np.unique(a["source"], axis=0)) == 300  # no replacement with enough points
    np.testing.assert_array_equal(
        FramePairs(kitchen, 1, range(100, 103), 300, seed=3, stride=4)[0]["source"], a["source"]
    )
    sub.set_epoch(1)
    assert not np.array_equal(sub[0]["source"], a["source"])

    norm = FramePairs(
        kitchen, gap=1, frames=range(100, 102), num_points=400, seed=1, normalize=True, stride=4
    )
    b, raw = norm[0], FramePairs(kitchen, gap=1, frames=range(100, 102), num_points=400, seed=1, stride=4)[0]
    src = b["source"].astype(np.float64)
    assert src.min() >= -1e-6 and src.max() <= 1 + 1e-6 and abs(np.ptp(src, axis=0).max() - 1) < 1e-6
    # Normalised pair + adjusted transform describe the same motion as the metric pair.
    back = move(b["transform"].astype(np.float64), src) * b["scale"] + b["offset"]
    np.testing.assert_allclose(back, move(raw["transform"].astype(np.float64), raw["source"]), atol=1e-4)
    np.testing.assert_allclose(b["target"] * b["scale"] + b["offset"], raw["target"], atol=1e-5)
    with pytest.raises(ConfigError):
        FramePairs(kitchen, gap=0)
    with pytest.raises(ConfigError):
        FramePairs(RGBDSequence.stairs(1), gap=3)  # 3 frames: no pair 3 apart


@needs_data
def test_fmr_pairs() -> None:
    seq = RGBDSequence.stairs(3)
    ds = FMRPairs(seq, frames=[0, 1, 2], num_points=256, seed=5, stride=4)
    for k in range(3):
        item = ds[k]
        assert item["source_index"] == item["target_index"] == k
        cloud = seq.points(k, stride=4).astype(np.float64)
        cloud = (cloud - cloud.min(0)) / np.ptp(cloud, axis=0).max()  # independent unit-box normalisation
        T = item["transform"].astype(np.float64)
        assert np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()) <= 45 + 1e-3
        assert np.linalg.norm(T[:3, 3]) <= 0.8 + 1e-6
        src = item["source"].astype(np.float64)
        tgt_obj = (item["target"] - T[:3, 3]) @ T[:3, :3]
        assert src.min() >= -1e-6 and src.max() <= 1 + 1e-6
        tree = cKDTree(cloud)
        assert tree.query(src)[0].max() < 1e-5 and tree.query(tgt_obj)[0].max() < 1e-4
        assert not np.allclose(np.sort(src, 0), np.sort(tgt_obj, 0), atol=1e-3)  # two different draws
    again = FMRPairs(seq, frames=[0, 1, 2], num_points=256, seed=5, stride=4)
    np.testing.assert_array_equal(again[1]["target"], ds[1]["target"])
    again.set_epoch(2)
    assert not np.allclose(again[1]["transform"], ds[1]["transform"])
    with pytest.raises(DataNotFoundError):
        FMRPairs(seq, frames=[0, 7])


def test_missing_data_and_env_override(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("GENREG_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(DataNotFoundError):
        RGBDSequence.redkitchen()
    with pytest.raises(DataNotFoundError):
        RGBDSequence(tmp_path / "nope", intrinsics=np.eye(3))
    seq_dir = tmp_path / "data" / "7scenes" / "stairs" / "seq-01"
    seq_dir.mkdir(parents=True)
    write_png16(seq_dir / "frame-000004.depth.png", np.full((6, 8), 1500))
    np.savetxt(seq_dir / "frame-000004.pose.txt", np.eye(4))
    monkeypatch.setenv("GENREG_DATA", str(tmp_path / "data"))
    seq = RGBDSequence.stairs(1, root="/not/used")  # the env wins, as in config.data_root
    assert seq.frame_indices == (4,) and seq.folder == seq_dir
    np.testing.assert_allclose(seq.points(4)[:, 2], 1.5)
    np.testing.assert_allclose(read_pose(seq_dir / "frame-000004.pose.txt"), np.eye(4))
    with pytest.raises(DataNotFoundError):  # no camera-intrinsics.txt in or above the folder
        RGBDSequence(seq_dir)
    with pytest.raises(ConfigError):
        RGBDSequence.open("office")
