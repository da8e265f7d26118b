"""Bag writer/reader round trip (rosbags, no ROS graph): mcap and sqlite3, points, colours, stamps, frames."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from genreg_core.data.rgbd import RGBDSequence
from genreg_ros.bag import (
    DEFAULT_FRAME_ID,
    DEFAULT_START_NS,
    BagWriter,
    Frame,
    cloud_message,
    read_bag,
    write_sequence_bag,
)
from genreg_ros.bag.make_bag import main as make_bag_main


@pytest.fixture(scope="module")
def redkitchen() -> RGBDSequence:
    return RGBDSequence.redkitchen()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_sequence_round_trip(tmp_path, redkitchen, storage):
    frames = [800, 802, 804, 806]  # a frame stride of 2 keeps the original 30 Hz timing
    info = write_sequence_bag(redkitchen, tmp_path / "bag", frames, pixel_stride=8, storage=storage)
    bag = read_bag(tmp_path / "bag")
    assert (tmp_path / "bag" / f"bag.{'mcap' if storage == 'mcap' else 'db3'}").is_file()
    assert bag.info == info and bag.frame_numbers == frames
    assert len(bag.clouds) == len(bag.poses) == 4
    for k, (f, cloud, pose) in enumerate(zip(frames, bag.clouds, bag.poses)):
        stamp = DEFAULT_START_NS + round((f - 800) * 1e9 / 30.0)
        assert cloud.stamp_ns == pose.stamp_ns == cloud.log_time_ns == stamp
        assert cloud.frame_id == pose.child == DEFAULT_FRAME_ID and pose.parent == "world"
        assert cloud.error is None and cloud.fields == ("x", "y", "z", "rgb")
        np.testing.assert_array_equal(cloud.points, redkitchen.points(f, 8))
        np.testing.assert_array_equal(cloud.colors, redkitchen.colors(f, 8))
        np.testing.assert_allclose(pose.matrix, redkitchen.pose(f), atol=1e-12)
    assert bag.clouds[1].stamp_ns - bag.clouds[0].stamp_ns == round(2e9 / 30)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_frames_round_trip_xyz_and_malformed(tmp_path, storage):
    rng = np.random.default_rng(0)
    frames = [Frame(i, 5_000_000_000 + i * 100_000_000, rng.normal(size=(50 + i, 3)).astype(np.float32),
                    pose=np.eye(4)) for i in range(3)]
    with BagWriter(tmp_path / "bag", storage, frame_id="cam", world_frame="map") as writer:
        for f in frames:
            writer.write_frame(f)
        good = cloud_message(9_000_000_000, "cam", frames[0].points)
        writer.write_cloud(dataclasses.replace(good, data=good.data[:100]))  # truncated data
        fields = [dataclasses.replace(f, name=n) for f, n in zip(good.fields, "abc")]
        writer.write_cloud(dataclasses.replace(good, fields=fields))  # no x/y/z fields
    bag = read_bag(tmp_path / "bag")
    assert [c.stamp_ns for c in bag.clouds] == [f.stamp_ns for f in frames] + [9_000_000_000] * 2
    for f, c in zip(frames, bag.clouds):
        np.testing.assert_array_equal(c.points, f.points)
        assert c.colors is None and c.fields == ("x", "y", "z") and c.frame_id == "cam"
    assert bag.poses[0].parent == "map" and bag.poses[0].child == "cam"
    assert [c.error for c in bag.clouds[3:]] == ["truncated_data", "missing_xyz"]
    assert bag.clouds[3].points is None and bag.frame_numbers == [0, 1, 2, 3, 4]  # no info: bag order


def test_make_bag_cli(tmp_path, capsys):
    out = tmp_path / "sun3d"
    args = ["--sequence", "sun3d-2", "--start", "3170", "--count", "3", "--stride", "5", "--pixel-stride", "16",
            "--storage", "sqlite3", "--rate", "10", "--out", str(out)]
    assert make_bag_main(args) == 0
    assert "3 frames 3170-3180" in capsys.readouterr().out
    bag = read_bag(out)
    assert bag.frame_numbers == [3170, 3175, 3180] and bag.info["sequence"] == "sun3d-2"
    assert bag.clouds[1].stamp_ns - bag.clouds[0].stamp_ns == 500_000_000  # 5 frames at 10 Hz
    assert all(c.colors is None for c in bag.clouds)  # SUN3D ships no colour
    assert make_bag_main(args) == 1  # the bag exists: refused without --overwrite
    assert "exists" in capsys.readouterr().err
