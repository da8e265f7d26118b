"""register_node as robots use it: the node in its own process and a client of this test's own:
time jumps, the initial guess (parameter, topics, frames, expiry), per-result quality (`pose` with its
covariance, `registration_status`, min_confidence) and the warning for a publisher that delivers nothing.

One node process (the shipped `7scenes` model) serves the module. Accuracy: SUN3D fragment 1, frames
935 -> 955 (a scene the models never saw) with the ground truth as the guess, and redkitchen frames.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from test_node import (
    SHIPPED_MODEL,
    SMALL_T,
    SRC_FRAME,
    TEST_PARAMS,
    TGT_FRAME,
    check_outputs,
    diag_values,
    errors,
    guess_param,
    make_pair,
    node_process,
    redkitchen_pair,
    stamp,
    wait_subscribed,
)

from genreg_core.data.rgbd import RGBDSequence
from genreg_core.data.synthetic_lidar import LidarSensor, make_scene, scan_pair
from genreg_ros.conversions import msg_to_matrix
from genreg_ros.pointcloud2 import xyz_to_msg

STALE_TIMEOUT = 1.0


@pytest.fixture(scope="module")
def robot(ros_namespace, tmp_path_factory):
    params = {**TEST_PARAMS, "model.checkpoint": SHIPPED_MODEL, "refine.method": "gicp",  # as config/genreg.yaml
              "diagnostics.stale_timeout": STALE_TIMEOUT}
    log = tmp_path_factory.mktemp("robot") / "node.log"
    with node_process(f"{ros_namespace}/robot", log, params) as (h, _proc, log_path):
        wait_subscribed(h, h.pub_source, h.pub_target)
        yield h, log_path


def test_a_matched_publisher_that_delivers_nothing_is_warned_once(robot):
    """Runs first: the client's publishers are matched but have sent nothing for the stale timeout."""
    h, log = robot
    deadline = time.monotonic() + 10
    while log.read_text().count("likely cause") < 2:  # one per input topic
        assert time.monotonic() < deadline, log.read_text()
        time.sleep(0.2)
    time.sleep(3 * STALE_TIMEOUT)
    lines = [ln for ln in log.read_text().splitlines() if "likely cause" in ln]
    assert len(lines) == 2, lines  # once per topic, not once per diagnostics period
    assert all("fastdds_large_clouds.xml" in ln and "docs/ros_node.md" in ln for ln in lines)
    s = h.status(after=time.monotonic())
    assert s.level == DiagnosticStatus.WARN and "publisher(s) on" in s.message


def _count(msgs, header: Header) -> int:
    return sum((m.header.stamp.sec, m.header.stamp.nanosec) == (header.stamp.sec, header.stamp.nanosec)
               for m in msgs)


def test_the_same_stamps_replayed_twice_are_registered_both_times(robot):
    h, log = robot
    before = h.counters()
    pairs = [make_pair(SMALL_T, 5000.0 + 1.5 * i, seed=i) for i in range(3)]  # 3 s back: a jump
    for replay in (1, 2):
        for src, tgt, _ in pairs:
            h.send(src, tgt)
            h.wait(lambda src=src, n=replay: _count(h.aligned, src.header) >= n and _count(h.transforms, src.header)
                   >= n, 20.0, f"pass {replay} output")
            with h.lock:
                tf = [m for m in h.transforms if m.header.stamp == src.header.stamp][-1]
            assert errors(msg_to_matrix(tf), SMALL_T)[0] < 1.0
    assert h.delta(before, "registered") == 6 and h.delta(before, "time_jump") == 1
    assert h.delta(before, "dropped.unmatched") == 0
    assert log.read_text().count("time jump:") == 1


def test_pose_and_registration_status_per_result(robot):
    h, _ = robot
    src, tgt, rec, T_true = redkitchen_pair(801, 800, 6000.0)
    h.send(src, tgt)
    aligned, tf = h.wait_output(src.header, timeout=30.0)
    check_outputs(aligned, tf, rec, src.header, T_true, src_frame="camera", tgt_frame="camera_previous",
                  rot_tol=0.6, trans_tol=0.01)
    h.wait(lambda: _count(h.poses, src.header), 5.0, "pose")
    with h.lock:
        pose = [m for m in h.poses if m.header.stamp == src.header.stamp][-1]
    assert pose.header.frame_id == "camera_previous"
    np.testing.assert_allclose(msg_to_matrix(pose.pose), msg_to_matrix(tf), atol=1e-9)
    C = np.asarray(pose.pose.covariance, dtype=np.float64).reshape(6, 6)
    assert np.isfinite(C).all() and np.abs(C).max() > 0, C
    np.testing.assert_allclose(C, C.T, rtol=1e-9, atol=1e-15)
    assert np.linalg.eigvalsh(C).min() >= -1e-12 * np.abs(C).max(), np.linalg.eigvalsh(C)
    assert np.sqrt(C[0, 0]) < 0.05 and np.sqrt(C[3, 3]) < np.radians(2)  # a good pair: cm and degrees
    status = h.result_for(src.header)
    v = diag_values(status)
    assert status.level == DiagnosticStatus.OK and v["published"] == "true"
    assert float(v["confidence"]) > 0.5 and 0.0 < float(v["fitness"]) <= 1.0 and 0 < float(v["inlier_rmse_m"]) < 0.05
    assert v["start"] in ("genreg", "guard") and v["initial_guess"] == "none"
    assert v["target_frame"] == "camera_previous" and v["source_frame"] == "camera"


def sun3d_pair(t: float):
    """SUN3D fragment 1: frame 935 (source) onto frame 955 (target), and T_955_935 from the dataset's poses."""
    seq = RGBDSequence.sun3d(1)
    assert np.allclose(seq.K[[0, 1], [0, 1]], 570.34, atol=0.01), seq.K
    src_pts, tgt_pts = seq.points(935, stride=4), seq.points(955, stride=4)
    hs, ht = stamp(t), stamp(t + 0.01)
    hs.frame_id, ht.frame_id = "camera", "camera_previous"
    return xyz_to_msg(hs, src_pts), xyz_to_msg(ht, tgt_pts), seq.relative_pose(935, 955)


def test_ground_truth_guess_on_sun3d_is_within_1_deg_and_3_cm(robot):
    h, _ = robot
    src, tgt, T_true = sun3d_pair(7000.0)
    (res,) = h.set_remote(Parameter("initial_guess", value=guess_param(T_true)))
    assert res.successful, res.reason
    try:
        h.send(src, tgt)
        _, tf = h.wait_output(src.header, timeout=30.0)
        assert diag_values(h.result_for(src.header))["initial_guess"] == "parameter"
        rot, trans = errors(msg_to_matrix(tf), T_true)
        print(f"SUN3D 935 -> 955, ground-truth guess: RE {rot:.3f} deg, TE {100 * trans:.2f} cm")
        assert rot < 1.0 and trans < 0.03, (rot, trans)
    finally:
        assert h.set_remote(Parameter("initial_guess", Parameter.Type.DOUBLE_ARRAY, []))[0].successful


def test_guess_parameter_is_used_and_resets_to_empty_like_ros2_param_set(robot):
    h, _ = robot
    assert h.set_remote(Parameter("initial_guess", value=guess_param(SMALL_T)))[0].successful
    src, tgt, _ = make_pair(SMALL_T, 7100.0)
    h.send(src, tgt)
    assert diag_values(h.result_for(src.header, timeout=20.0))["initial_guess"] == "parameter"
    # `ros2 param set /register_node initial_guess []` sends an empty *bool* array.
    (res,) = h.set_remote(Parameter("initial_guess", Parameter.Type.BOOL_ARRAY, []))
    assert res.successful, res.reason
    src, tgt, _ = make_pair(SMALL_T, 7101.0)
    h.send(src, tgt)
    assert diag_values(h.result_for(src.header, timeout=20.0))["initial_guess"] == "none"


def _guess_msg(T, parent, child) -> TransformStamped:
    g = TransformStamped(header=Header(frame_id=parent), child_frame_id=child)
    g.transform.translation.x, g.transform.translation.y, g.transform.translation.z = map(float, T[:3, 3])
    r = g.transform.rotation
    r.x, r.y, r.z, r.w = map(float, Rotation.from_matrix(T[:3, :3]).as_quat())
    return g


def _initialpose(T, frame) -> PoseWithCovarianceStamped:
    msg = PoseWithCovarianceStamped(header=Header(frame_id=frame))
    g = _guess_msg(T, frame, "")
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = g.transform.translation.x, g.transform.translation.y, g.transform.translation.z
    q.x, q.y, q.z, q.w = g.transform.rotation.x, g.transform.rotation.y, g.transform.rotation.z, g.transform.rotation.w
    return msg


def _register(h, t) -> dict[str, str]:
    src, tgt, _ = make_pair(SMALL_T, t, seed=5)
    h.send(src, tgt)
    return diag_values(h.result_for(src.header, timeout=20.0))


def test_topic_guesses_check_frames_expire_and_reset(robot):
    h, _ = robot
    before = h.counters()
    h.pub_guess.publish(_guess_msg(SMALL_T, "odom", SRC_FRAME))  # wrong parent frame
    time.sleep(0.3)
    assert _register(h, 8000.0)["initial_guess"] == "none"
    assert h.delta(before, "dropped.initial_guess_frames") == 1
    h.pub_guess.publish(_guess_msg(SMALL_T, TGT_FRAME, SRC_FRAME))
    time.sleep(0.3)
    assert _register(h, 8001.0)["initial_guess"] == "initial_guess"
    (res,) = h.set_remote(Parameter("initial_guess_timeout", value=0.5))
    assert res.successful
    try:
        h.pub_initialpose.publish(_initialpose(SMALL_T, TGT_FRAME))  # RViz's 2D Pose Estimate
        time.sleep(0.2)
        assert _register(h, 8002.0)["initial_guess"] == "initialpose"
        time.sleep(0.6)
        assert _register(h, 8003.0)["initial_guess"] == "none"  # expired
        h.pub_initialpose.publish(_initialpose(SMALL_T, TGT_FRAME))
        time.sleep(0.2)
        assert h.call(Trigger, "reset").success
        assert _register(h, 8004.0)["initial_guess"] == "none"  # reset forgets it
    finally:
        assert h.set_remote(Parameter("initial_guess_timeout", value=5.0))[0].successful
    assert h.delta(before, "reset") == 1


def test_min_confidence_rejects_and_says_so(robot):
    h, _ = robot
    before = h.counters()
    assert h.set_remote(Parameter("min_confidence", value=1.0))[0].successful
    try:
        src, tgt, _ = make_pair(SMALL_T, 9000.0)
        h.send(src, tgt)
        status = h.result_for(src.header, timeout=20.0)
        v = diag_values(status)
        assert status.level == DiagnosticStatus.ERROR and v["published"] == "false" and "min_confidence" in status.message
        time.sleep(0.3)
        assert _count(h.aligned, src.header) == 0 and _count(h.poses, src.header) == 0
        assert h.delta(before, "failed.low_confidence_rejected") == 1 and h.delta(before, "registered") == 0
    finally:
        assert h.set_remote(Parameter("min_confidence", value=TEST_PARAMS["min_confidence"]))[0].successful


def test_synthetic_lidar_scans_with_dual_returns_and_misses_register_through_the_node(robot):
    """Two scans of the synthetic street LiDAR 0.5-1 m apart, the source kidnapped (up to 45 deg, 2 m), with
    4 % dual returns and misses emitted as (0, 0, 0): the node publishes the true transform (it counted
    every such pair as internal_error)."""
    h, _ = robot
    sensor = LidarSensor.uniform(32, (-15.0, 25.0), 1024, max_range=40.0, keep_misses=True)  # 9 % misses
    pair = scan_pair(make_scene("street"), np.random.default_rng(21), sensor)
    hs, ht = stamp(7200.0), stamp(7200.01)
    hs.frame_id, ht.frame_id = SRC_FRAME, TGT_FRAME
    h.send(xyz_to_msg(hs, pair.source.points), xyz_to_msg(ht, pair.target.points))
    _, tf = h.wait_output(hs, timeout=30.0)
    rot, trans = errors(msg_to_matrix(tf), pair.T_target_source)
    assert rot < 2.0 and trans < 0.3, (rot, trans)
