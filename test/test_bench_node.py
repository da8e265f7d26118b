"""scripts/bench_node.py soak: the clouds it replays and their ground truth (no node, no DDS traffic)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2

from genreg_core.config import data_root
from genreg_ros.conversions import stamp_ns
from genreg_ros.pointcloud2 import read_points
from genreg_ros.replay.harness import restamp

REPO = Path(__file__).resolve().parent.parent
needs_data = pytest.mark.skipif(not (data_root() / "7scenes").is_dir(), reason="RGB-D data not available")


@pytest.fixture()
def bench(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "57")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    spec = importlib.util.spec_from_file_location("bench_node", REPO / "scripts" / "bench_node.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_node", module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _decode(raw: bytes, stamp: int) -> tuple[PointCloud2, np.ndarray]:
    msg = deserialize_message(restamp(raw, stamp), PointCloud2)
    return msg, read_points(msg).points


def test_synthetic_pair_ground_truth_maps_source_onto_target(bench):
    clouds = bench.synthetic_clouds(2000)
    (t,) = clouds.pairs
    src_msg, src = _decode(t.source_raw, 123_456_789_000)
    tgt_msg, tgt = _decode(t.target_raw, 123_456_789_000)
    assert stamp_ns(src_msg.header) == stamp_ns(tgt_msg.header) == 123_456_789_000
    assert (src_msg.header.frame_id, tgt_msg.header.frame_id) == (t.pair.source_frame_id, t.pair.target_frame_id)
    T = t.pair.T_gt
    np.testing.assert_allclose(src @ T[:3, :3].T + T[:3, 3], tgt, atol=1e-4)


@needs_data
def test_sequence_pairs_are_consecutive_frames_with_relative_pose(bench):
    from genreg_core.data.rgbd import RGBDSequence

    clouds = bench.sequence_clouds("redkitchen", 800, 3, 16, 1)
    assert [(t.pair.target_frame, t.pair.source_frame) for t in clouds.pairs] == [(800, 801), (801, 802)]
    assert clouds.pairs[0].source_raw is clouds.pairs[1].target_raw  # each frame serialised once
    seq = RGBDSequence.redkitchen()
    for t in clouds.pairs:
        np.testing.assert_allclose(t.pair.T_gt, seq.relative_pose(t.pair.source_frame, t.pair.target_frame))
        msg, points = _decode(t.source_raw, 42)
        assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb"]
        assert len(points) == t.pair.source_points == len(seq.points(t.pair.source_frame, 16))


def test_node_args_are_key_value_parameters(bench):
    assert bench.parse_node_args(["refine.method:=none", "seed:=1"]) == {"refine.method": "none", "seed": "1"}
    with pytest.raises(SystemExit):
        bench.parse_node_args(["-p"])
