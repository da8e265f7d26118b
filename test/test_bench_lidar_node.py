"""scripts/bench_lidar_node.py: its accounting of the node's answers and the scans it sends (no node, no DDS
traffic)."""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2

from genreg_core.data import lidar_world as lw
from genreg_core.data.synthetic_lidar import DRIVER_POINT
from genreg_core.geometry import make_transform
from genreg_ros.pointcloud2 import read_points
from genreg_ros.replay.harness import Output

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture()
def bench(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "58")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    # importing bench_lidar_map sets these; restored after the test
    monkeypatch.setenv("OMP_WAIT_POLICY", os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    monkeypatch.setenv("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "2"))
    monkeypatch.syspath_prepend(str(REPO / "scripts"))
    spec = importlib.util.spec_from_file_location("bench_lidar_node", REPO / "scripts" / "bench_lidar_node.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_lidar_node", module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_a_phase_counts_each_scan_once_by_its_answer_and_its_error_against_the_truth(bench):
    """Five scans of one phase (and one of another): published right, published 0.3 m off (wrong), superseded,
    never answered (lost), published 5 cm off; each counted once, the errors from the published transforms."""
    truth = [make_transform(np.eye(3), [float(k), 2.0, 1.8]) for k in range(6)]
    off = [0.0, 0.3, None, None, 0.05, 0.0]  # the published pose's offset along y (None: nothing published)
    sent = [bench.Sent(1000 + k, "walk" if k < 5 else "drive", truth[k], 0.0) for k in range(6)]
    status = {1000: {"published": "true", "latency_ms": "10", "jumped": "true"}, 1001: {"published": "true", "latency_ms": "30"},
              1002: {"published": "false", "reason": "dropped.superseded"},
              1004: {"published": "true", "latency_ms": "20"}, 1005: {"published": "true", "latency_ms": "99"}}
    transforms = {1000 + k: Output(0.0, "map", "velodyne", truth[k] @ make_transform(np.eye(3), [0.0, d, 0.0]))
                  for k, d in enumerate(off) if d is not None}
    client = SimpleNamespace(lock=threading.Lock(), status=status, transforms=transforms)
    run = bench.answers(SimpleNamespace(client=client, sent=sent))
    f = bench.phase_figures(run, "walk")
    assert (f["sent"], f["answered"], f["lost"], f["published"], f["wrong"], f["jumped"]) == (5, 4, 1, 3, 1, 1)
    records = [bench.scan_record(a) for a in run]  # the JSON's scans: each with its status and errors
    assert [r["stamp"] for r in records] == [1000 + k for k in range(6)] and records[5]["phase"] == "drive"
    assert records[1]["te_m"] == pytest.approx(0.3) and records[1]["status"] == status[1001]
    assert records[2]["te_m"] is None and records[2]["status"]["reason"] == "dropped.superseded"
    assert records[3] == {"stamp": 1003, "phase": "walk", "status": {}, "re_deg": None, "te_m": None}
    assert f["reasons"] == {"dropped.superseded": 1} and f["within_0.1_m"] == "2/3" and f["first_published"] == 0
    assert f["te_median_m"] == pytest.approx(0.05) and f["te_max_m"] == pytest.approx(0.3)
    assert f["latency_ms_p50"] == pytest.approx(20.0)


def test_scans_go_out_as_a_driver_publishes_them(bench):
    """A serialised scan decodes to the driver's 22-byte point with the misses as NaN: its finite points are the
    revolution's hits (cast again with the same rng, misses kept), in the sensor frame."""
    world = lw.campus_world(0, (1, 1))
    pose = bench.walk_poses(world, 1)
    sensor = bench.SCAN_SENSOR
    (raw,) = bench.serialised(world, pose, np.random.default_rng(3), sensor, "test")
    msg = deserialize_message(raw, PointCloud2)
    assert msg.header.frame_id == bench.SENSOR_FRAME and msg.point_step == DRIVER_POINT.itemsize
    assert [f.name for f in msg.fields] == list(DRIVER_POINT.names) and not msg.is_dense
    cast = lw.world_scan(world, pose[0], np.random.default_rng(3), dataclasses.replace(sensor, keep_misses=True))
    hits = cast.points[cast.points.any(axis=1)]  # a miss is emitted as (0, 0, 0)
    assert len(hits) < len(cast.points)
    decoded = read_points(msg)
    assert decoded.num_input == len(cast.points) and len(decoded.points) == len(hits)
    np.testing.assert_allclose(np.sort(decoded.points, axis=0), np.sort(hits, axis=0))


def test_the_run_is_drawn_scan_by_scan_from_the_same_answers(bench, tmp_path):
    """`answers` pairs each scan sent with its status and, when published, its errors against the truth (a
    scan whose transform never came is not published); `plot_run` draws them into a PNG."""
    truth = [make_transform(np.eye(3), [float(k), 0.0, 0.0]) for k in range(4)]
    sent = [bench.Sent(10 + k, "drive" if k < 2 else "walk", truth[k], 0.1 * k) for k in range(4)]
    status = {10: {"published": "true", "latency_ms": "15"}, 11: {"published": "true", "latency_ms": "40"},
              12: {"published": "false", "reason": "failed.low_confidence_rejected", "latency_ms": "200"}}
    transforms = {10: Output(0.0, "map", "velodyne", truth[0] @ make_transform(np.eye(3), [0.02, 0.0, 0.0]))}
    client = SimpleNamespace(lock=threading.Lock(), status=status, transforms=transforms)
    run = bench.answers(SimpleNamespace(client=client, sent=sent))
    assert [a.answered for a in run] == [True, True, True, False]
    assert run[0].errors == pytest.approx((0.0, 0.02), abs=1e-9) and run[1].errors is None  # no transform came
    assert [a.latency_ms for a in run] == [15.0, 40.0, 200.0, None]
    path = tmp_path / "run.png"
    bench.plot_run(run, path, "test")
    import matplotlib.image

    height, width, _ = matplotlib.image.imread(path).shape
    assert (width, height) == (1100, 660)


def test_the_operators_click_is_off_to_the_left_turned_and_ahead_along_the_heading(bench):
    """The kidnap phase's `initialpose`: `OPERATOR_OFF` to the robot's left and turned, and `--click-ahead` m along
    its heading; read back by the node's own conversion."""
    from genreg_ros.conversions import msg_to_matrix

    heading = np.radians(30.0)
    truth = make_transform(np.array([[np.cos(heading), -np.sin(heading), 0.0], [np.sin(heading), np.cos(heading), 0.0],
                                     [0.0, 0.0, 1.0]]), np.array([5.0, -2.0, 0.6]))
    left, degrees = bench.OPERATOR_OFF
    for ahead in (0.0, 2.0):
        T = msg_to_matrix(bench.operator_pose(truth, ahead).pose)
        local = np.linalg.inv(truth) @ T  # the click in the robot's frame
        assert np.allclose(local[:3, 3], [ahead, left, 0.0], atol=1e-9)
        assert np.degrees(np.arctan2(local[1, 0], local[0, 0])) == pytest.approx(degrees)
