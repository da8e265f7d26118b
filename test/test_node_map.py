"""register_node's map mode in its own process, driven by a client of this test's own: scans of redkitchen
localised in a map fused from its validation frames, against the ground-truth poses (the map frame is the
dataset's world frame, so a scan's true pose in the map is `pose(i)`).

The node runs with config/genreg_map.yaml as shipped (plus a short diagnostics period). The map is published
once on `target_cloud` by a reliable, transient_local publisher before the node exists (a latched map). The
scans are a recorded stream: a bag (genreg_ros.bag.writer, with the ground-truth poses beside them) of a
camera that tracks, is kidnapped, looks at another building and comes back; each is replayed as recorded
(its serialised bytes) by a best-effort publisher (SensorDataQoS, as a camera driver's), one at a time. What is checked: the first scan
is placed without a guess (`localization: global`), the next ones track, a kidnapped camera is relocalised
within three scans, an off-map scan (SUN3D) publishes no pose and tracking turns lost, `~/relocalize`
localises the next scan without a guess, and RViz's `initialpose` is the next scan's guess. Another test
starts the node in this process with `map.localization` parameters and checks that its MapLocalizer uses them.
"""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from test_node import (
    SMALL_T,
    diag_values,
    errors,
    make_pair,
    node_process,
    running_node,
    stamp,
    wait_subscribed,
)

from genreg_core.config import LocalizationConfig
from genreg_core.data.rgbd import RGBDSequence
from genreg_core.geometry import apply_transform
from genreg_ros.bag.reader import BagData, read_bag
from genreg_ros.bag.writer import BagWriter, Frame
from genreg_ros.config import CONFIG_DIR
from genreg_ros.conversions import matrix_to_pose_msg, msg_to_matrix
from genreg_ros.pointcloud2 import xyz_to_msg

MAP_FRAMES = range(800, 1000, 10)  # redkitchen validation frames fused into the map (every 10th of 800-990)
STRIDE = 4
MAP_FRAME_ID, CAMERA = "map", "camera"
MAX_RE, MAX_TE = 2.0, 0.05  # deg, m
PARAMS = {"diagnostics.period": 0.2}  # config/genreg_map.yaml otherwise


def fused_map(seq: RGBDSequence) -> np.ndarray:
    """The map frames' points moved by their poses into the world frame, concatenated, voxelised to 2 cm."""
    world = np.concatenate([apply_transform(seq.pose(i), seq.points(i, stride=STRIDE).astype(np.float64))
                            for i in MAP_FRAMES])
    return np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world)).voxel_down_sample(0.02).points)


STREAM = [("redkitchen", i) for i in (805, 806, 807, 975, 977, 979)] + [("sun3d-1", 940)] * 2 + [
    ("redkitchen", i) for i in (983, 985, 987, 945)]  # the recorded camera: (sequence, frame)


def record(path, seq: RGBDSequence) -> BagData:
    """The bag of STREAM: clouds stamped 101 s, 102 s, ... in the camera frame, and T_map_camera (the map
    frame is the dataset's world frame) for the scans of the mapped sequence; read back."""
    sun3d = RGBDSequence.sun3d(1)
    with BagWriter(path, frame_id=CAMERA, world_frame=MAP_FRAME_ID) as bag:
        for k, (name, i) in enumerate(STREAM):
            on_map = name == "redkitchen"
            points = (seq if on_map else sun3d).points(i, stride=STRIDE)
            bag.write_frame(Frame(i, int((101 + k) * 1e9), points, pose=seq.pose(i) if on_map else None))
    return read_bag(path, decode=False)


@pytest.fixture(scope="module")
def mapped(ros_namespace, tmp_path_factory):
    """The node in map mode, its latched map published before it started, and a best-effort scan publisher."""
    seq = RGBDSequence.redkitchen()
    map_msg = xyz_to_msg(stamp(1.0), fused_map(seq))
    map_msg.header.frame_id = MAP_FRAME_ID
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    held = {}

    def publish_map(h):  # before the node exists: only transient_local durability can deliver it
        held["pub"] = h.helper.create_publisher(PointCloud2, "target_cloud", latched)
        held["pub"].publish(map_msg)
        held["scans"] = h.helper.create_publisher(PointCloud2, "source_cloud", qos_profile_sensor_data)

    log = tmp_path_factory.mktemp("map") / "node.log"
    with node_process(f"{ros_namespace}/map", log, PARAMS, before=publish_map,
                      params_file=CONFIG_DIR / "genreg_map.yaml") as (h, _proc, log_path):
        wait_subscribed(h, held["scans"], held["pub"])
        h.wait(lambda: any(diag_values(s).get("received.target") == "1" for m in h.diagnostics for s in m.status),
               15.0, "the latched map received")
        yield h, record(tmp_path_factory.mktemp("bag") / "scans", seq), held["scans"], log_path


class Scans:
    """The bag's scans replayed one at a time (each waits for its registration_status), in order; a scan
    may be skipped (the stamps still only grow)."""

    def __init__(self, h, pub, bag: BagData) -> None:
        self.h, self.pub, self.bag, self.next = h, pub, bag, 0
        self.t = 0.0  # the last stamp sent, s

    def send(self, frame: int) -> tuple[dict[str, str], np.ndarray | None, np.ndarray | None]:
        """(registration_status values, the published pose T_map_camera or None, the bag's truth or None) of
        the next recorded scan of this frame."""
        k = next(k for k in range(self.next, len(STREAM)) if STREAM[k][1] == frame)
        self.next = k + 1
        cloud = self.bag.clouds[k]
        assert cloud.frame_id == CAMERA
        self.t = cloud.stamp_ns / 1e9
        header = stamp(self.t)
        self.pub.publish(cloud.raw)  # the recorded bytes (CDR), as a bag player sends them
        truth = self.bag.pose_at(cloud.stamp_ns)
        result = self.h.result_for(header, timeout=60.0)
        status = {**diag_values(result), "message": result.message}
        assert status["target_frame"] == MAP_FRAME_ID and status["source_frame"] == CAMERA, status
        if status["published"] != "true":
            return status, None, truth
        key = (header.stamp.sec, header.stamp.nanosec)
        find = lambda: [m for m in self.h.poses if (m.header.stamp.sec, m.header.stamp.nanosec) == key]
        self.h.wait(find, 10.0, "the scan's pose")
        with self.h.lock:
            return status, msg_to_matrix(find()[-1].pose), truth


def check_pose(T: np.ndarray | None, truth: np.ndarray, what: str, status: dict[str, str]) -> None:
    assert T is not None, f"{what}: no pose published ({status})"
    re, te = errors(T, truth)
    assert re < MAX_RE and te < MAX_TE, f"{what}: RE {re:.2f} deg, TE {100 * te:.1f} cm ({status})"


def test_scans_are_localised_tracked_relocalised_and_off_map_scans_publish_nothing(mapped):
    h, bag, pub, log = mapped
    scans = Scans(h, pub, bag)
    t0 = time.monotonic()

    status, T, truth = scans.send(805)  # the first scan: no guess
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    assert status["message"].startswith("global: published"), status
    check_pose(T, truth, "first scan", status)
    for i in (806, 807):  # from the last accepted pose (a camera at its 30 Hz)
        status, T, truth = scans.send(i)
        assert status["localization"] == "tracking" and status["initial_guess"] == "last_result", status
        check_pose(T, truth, f"tracked scan {i}", status)

    # kidnapped: the camera jumps about 1 m and 35 deg (frames from another part of the sequence)
    assert errors(bag.pose_at(bag.clouds[3].stamp_ns), bag.pose_at(bag.clouds[2].stamp_ns))[0] > 30.0
    states = []
    for n, i in enumerate((975, 977, 979)):
        status, T, truth = scans.send(i)
        states.append(status["localization"])
        if T is not None:
            check_pose(T, truth, f"kidnapped scan {i}", status)  # every pose published is right
            break
    else:
        raise AssertionError(f"the kidnapped camera was not relocalised within 3 scans: {states}")
    assert n == 0 or status["localization"] == "global", states

    # off the map (another building): no pose, tracking lost after map.lost_after (2) misses
    for expected in ("tracking", "lost"):
        status, T, truth = scans.send(940)
        assert truth is None and T is None and status["published"] == "false", status
        assert status["localization"] == expected, status
    assert status["message"].startswith("lost: rejected: confidence"), status
    diag = diag_values(h.status(after=time.monotonic()))
    assert diag["localization"] == "lost" and int(diag["tracking_lost"]) >= 1, diag

    status, T, truth = scans.send(983)  # back on the map: lost -> global
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    check_pose(T, truth, "scan after lost", status)
    status, T, truth = scans.send(985)
    assert status["localization"] == "tracking", status
    check_pose(T, truth, "tracked scan 985", status)

    response = h.call(Trigger, "relocalize")
    assert response.success, response.message
    status, T, truth = scans.send(987)
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    check_pose(T, truth, "scan after ~/relocalize", status)

    # RViz's 2D Pose Estimate: the next scan's guess (a pose 5 cm and a little rotation off the truth)
    guess = bag.pose_at(bag.clouds[-1].stamp_ns).copy()
    guess[:3, 3] += [0.03, -0.03, 0.03]
    h.pub_initialpose.publish(matrix_to_pose_msg(guess, Header(stamp=stamp(scans.t).stamp, frame_id=MAP_FRAME_ID),
                                                 None))
    time.sleep(0.5)
    status, T, truth = scans.send(945)
    assert status["localization"] == "tracking" and status["initial_guess"] == "initialpose", status
    check_pose(T, truth, "scan from initialpose", status)
    assert time.monotonic() - t0 < 60.0
    text = log.read_text()
    assert "tracking lost" in text and "relocalize (relocalize service)" in text, text[-3000:]


def test_map_settings_given_as_parameters_are_the_map_localizers(ros_namespace, untrained_checkpoint, capfd):
    """`map.localization.*` reach the node's MapLocalizer: a map resolution given as a parameter is the one the
    scans are voxelised to (the node logs it when the map is ready), not the map's measured spacing (0.056 m)."""
    settings = {"map.enabled": True, "map.localization.voxel_size": 0.15, "map.localization.candidates": 2}
    with running_node(f"{ros_namespace}/map_settings", untrained_checkpoint, **settings) as h:
        assert h.node.config.map.localization == LocalizationConfig(voxel_size=0.15, candidates=2)
        source, target, _ = make_pair(SMALL_T, 200.0, n=2000)
        wait_subscribed(h, h.pub_source, h.pub_target)
        h.pub_target.publish(target)
        h.wait(lambda: any(diag_values(s).get("received.target") == "1" for m in h.diagnostics for s in m.status),
               15.0, "the map received")
        h.pub_source.publish(source)
        status = diag_values(h.result_for(source.header, timeout=60.0))
        assert status["localization"] == "global" and status["target_frame"] == target.header.frame_id, status
    assert "map of 2000 points in frame 'map' ready (resolution 0.15 m)" in capfd.readouterr().err
