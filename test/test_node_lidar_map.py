"""register_node localising a spinning LiDAR in a prior LiDAR map, in its own process, against the true poses.

The world is a synthetic campus (`genreg_core.data.lidar_world.campus_world`, one city block ringed by
streets; the northern street lined by identical terraced houses repeating every 7 m). The map is fused from
survey scans every 3 m along its roads and corridors (the world's own map cache under cache/lidar_world),
written to a PLY file and given as `target_file`; the node runs with config/genreg_lidar_map.yaml as shipped
(plus a short diagnostics period). Scans are VLP-32-like revolutions with moving cars and people, published
in the sensor frame at 10 Hz by a best-effort publisher (SensorDataQoS) as a driver sends them
(`LidarScan.records`): x, y, z, intensity, ring (uint16) and time (float32) packed in 22 bytes (a time field
at an unaligned offset), misses as NaN points, `is_dense` false. The map frame is the world frame, so a
scan's true pose in the map is the pose it was cast from (`sensor_pose`), known to this test only.

The stream (`run`): the vehicle stands at its start on the southern street until the node has placed it
(the first scan without a guess) and tracks it; drives east 1 m per scan; is kidnapped to the western
street, turned 90 deg, and stands there until the node has placed it again; drives on south; then the node
is asked to relocalise (`~/relocalize`) while the vehicle stands in the terraced street, where a scan fits
the map equally well shifted by whole houses. Scans the node is too busy to take are superseded (a newer one
replaces the waiting one). Each test below checks one property of that one run.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from test_node import apply, diag_values, errors, node_process, stamp, wait_subscribed
from test_node_map import MAP_FRAME_ID

from genreg_core.data.lidar_world import (
    SURVEY_SENSOR,
    World,
    cached_map,
    campus_world,
    sensor_pose,
    world_scan,
)
from genreg_core.data.synthetic_lidar import DRIVER_POINT
from genreg_ros.config import CONFIG_DIR
from genreg_ros.conversions import msg_to_matrix, stamp_ns
from genreg_ros.pointcloud2 import array_to_msg, read_points
from genreg_ros.tracking import TRACKED

REPO = Path(__file__).resolve().parent.parent
LIDAR = "velodyne"
MAX_RE, MAX_TE = 2.0, 0.25  # deg, m: a published pose outside either is wrong
PERIOD = 0.1  # s: a 10 Hz LiDAR
SPEED = 1.0  # m per scan while driving (10 m/s)
HEIGHT = 1.8  # m: the sensor above the road, as the survey's
LANE = 0.8  # m: the vehicle's offset from the street's centre-line
PARAMS = {"diagnostics.period": 0.2}  # config/genreg_lidar_map.yaml otherwise
STATUS_DEPTH = 1000  # the test's registration_status history
SLIDE = re.compile(r"translation along \((-?[\d.]+), (-?[\d.]+), (-?[\d.]+)\) to a rival pose ([\d.]+) m away")


@dataclass(frozen=True)
class Scan:
    """One revolution: its records (DRIVER_POINT, sensor frame) and its true pose T_map_sensor."""

    records: np.ndarray
    truth: np.ndarray


@dataclass(frozen=True)
class Sent:
    """A scan as published: its stamp (sec, nanosec), the phase of the run and the scan."""

    key: tuple[int, int]
    phase: str
    scan: Scan

    @property
    def truth(self) -> np.ndarray:
        return self.scan.truth


@dataclass
class Run:
    """What the node answered to the stream: every scan sent, its registration_status (values plus
    `message`) and published pose by stamp, and the diagnostics and the node's log at the end."""

    sent: list[Sent]
    messages: int  # registration_status messages received
    statuses: dict[tuple[int, int], dict[str, str]]
    poses: dict[tuple[int, int], object]  # PoseWithCovarianceStamped
    aligned: dict[tuple[int, int], PointCloud2]
    diagnostics: dict[str, str]
    log: str
    map_cloud: PointCloud2 | None = None  # the latched map_cloud, as a subscriber that joins late gets it


def driver_records(world: World, pose: np.ndarray, seed: int) -> np.ndarray:
    """A scan as a driver publishes it: every ray of the revolution (misses as NaN), ring and firing time."""
    return world_scan(world, pose, np.random.default_rng(seed),
                      dataclasses.replace(SURVEY_SENSOR, keep_misses=True)).records()


def street_poses(world: World) -> dict[str, Callable[[float], np.ndarray]]:
    """T_map_sensor along the streets as a function of the position along them: the southern street driving
    east, the western street driving south (from its middle), the terraced northern street driving west."""
    xs = sorted(float(r[0, 0]) for r in world.roads if np.isclose(r[0, 0], r[-1, 0]))
    ys = sorted(float(r[0, 1]) for r in world.roads if np.isclose(r[0, 1], r[-1, 1]))
    assert world.terrace is not None and np.isclose(world.terrace[0, 1], ys[-1])
    return {
        "south": lambda x: sensor_pose(x, ys[0] + LANE, HEIGHT, 0.02),
        "west": lambda y: sensor_pose(xs[0] - LANE, y, HEIGHT, -np.pi / 2 - 0.03),
        "terrace": lambda x: sensor_pose(x, ys[-1] - LANE, HEIGHT, np.pi + 0.02),
    }


@pytest.fixture(scope="session")
def campus(tmp_path_factory) -> tuple[World, Path]:
    """The campus world and its map as a PLY file (metres, world frame), built once (cached under cache/)."""
    world = campus_world(seed=0, blocks=(1, 1))
    points = cached_map(world, spacing=3.0, voxel=0.2, cache_dir=REPO / "cache" / "lidar_world")
    path = tmp_path_factory.mktemp("lidar_map") / "campus.ply"
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    assert o3d.io.write_point_cloud(str(path), cloud)
    return world, path


def phase_scans(world: World) -> dict[str, list[Scan]]:
    """The scans of each phase of the stream (a standing phase: two revolutions at one place, sent in turn)."""
    street = street_poses(world)
    where = {
        "start": [street["south"](6.0)] * 2,
        "drive": [street["south"](7.0 + SPEED * k) for k in range(12)],
        "kidnap": [street["west"](8.0)] * 2,
        "drive_on": [street["west"](7.0 - SPEED * k) for k in range(6)],
        "terrace": [street["terrace"](0.0)] * 2,
    }
    return {phase: [Scan(driver_records(world, T, seed=100 * n + k), T) for k, T in enumerate(poses)]
            for n, (phase, poses) in enumerate(where.items())}


class Stream:
    """Scans published at 10 Hz in the sensor frame, stamped 0.1 s apart; what the node answers is read back
    by stamp."""

    def __init__(self, h, pub, statuses: list[DiagnosticArray], t0: float = 1000.0) -> None:
        self.h, self.pub, self.results, self.t, self.sent = h, pub, statuses, t0, []
        self.next_at = time.monotonic()
        self.children: set[str] = set()  # the child frames of the transforms published (`lidar_node`)
        self.run: Run | None = None  # what the node answered, once it stopped (`lidar_node`)
        self.odometry: Callable[[object, Scan], None] | None = None  # publishes the odometry of a scan's stamp

    def publish(self, scan: Scan, phase: str) -> None:
        time.sleep(max(0.0, self.next_at - time.monotonic()))
        self.next_at = max(self.next_at + PERIOD, time.monotonic())
        header = stamp(self.t)
        header.frame_id = LIDAR
        if self.odometry is not None:  # the odometry at the scan's stamp, sent before the scan
            self.odometry(header, scan)
        self.pub.publish(array_to_msg(header, scan.records, is_dense=False))
        self.sent.append(Sent((header.stamp.sec, header.stamp.nanosec), phase, scan))
        self.t += PERIOD

    def statuses(self) -> dict[tuple[int, int], dict[str, str]]:
        """Each registration_status received (values plus `message`) by its scan's stamp."""
        with self.h.lock:
            return {(m.header.stamp.sec, m.header.stamp.nanosec): {**diag_values(m.status[0]),
                                                                   "message": m.status[0].message}
                    for m in self.results}

    def registered(self, phase: str, localization: str | None = None) -> int:
        """How many of the phase's scans the node has registered (and published, in this state if given)."""
        keys = {s.key for s in self.sent if s.phase == phase}
        return sum(1 for k, v in self.statuses().items() if k in keys and v.get("published") == "true"
                   and localization in (None, v.get("localization")))

    def drive(self, scans: list[Scan], phase: str) -> None:
        for scan in scans:
            self.publish(scan, phase)

    def stand(self, scans: list[Scan], phase: str, until: Callable[[], bool], timeout: float) -> None:
        """Publish the phase's scans in turn until `until()` holds or `timeout` s passed (the checks say
        what was missing)."""
        deadline = time.monotonic() + timeout
        k = 0
        while not until() and time.monotonic() < deadline:
            self.publish(scans[k % len(scans)], phase)
            k += 1

    def settle(self, timeout: float = 30.0) -> None:
        """Wait until every scan the node received (its diagnostics' received.source, counted after the last
        scan was sent) has its registration_status."""
        time.sleep(0.5)
        deadline = time.monotonic() + timeout
        while len(self.statuses()) < int(diag_values(self.h.status(after=time.monotonic()))["received.source"]):
            assert time.monotonic() < deadline, "a registration_status missing for a scan the node received"


@contextmanager
def lidar_node(ros_namespace: str, name: str, params: dict, tmp_path_factory, cast: Callable[[], dict],
               also: Callable[[object], None] | None = None):
    """register_node in its own process with config/genreg_lidar_map.yaml and `params`, a best-effort scan
    publisher and a deep registration_status subscription (every status of a burst: those of the scans
    superseded during one slow localisation come at once); `cast()` makes the scans while the node starts;
    `also(harness)` adds a test's own publishers and subscriptions. Yields (Stream, scans) once
    the node is up and subscribed; `stream.run` (after the block) is what it answered."""
    held: dict = {}

    def scan_publisher(h):
        held["pub"] = h.helper.create_publisher(PointCloud2, "source_cloud", qos_profile_sensor_data)
        h.helper.create_subscription(DiagnosticArray, "registration_status", h._rec(held.setdefault("statuses", [])),
                                     QoSProfile(depth=STATUS_DEPTH, reliability=ReliabilityPolicy.RELIABLE))
        if also is not None:
            also(h)

    log = tmp_path_factory.mktemp(name) / "node.log"
    with node_process(f"{ros_namespace}/{name}", log, params, before=scan_publisher,
                      params_file=CONFIG_DIR / "genreg_lidar_map.yaml", ready=False) as (h, proc, log_path):
        scans = cast()
        h.wait(lambda: h.diagnostics or proc.poll() is not None, 60.0, "the node's diagnostics (start-up)")
        assert proc.poll() is None, log_path.read_text()
        wait_subscribed(h, held["pub"])
        stream = Stream(h, held["pub"], held["statuses"])
        yield stream, scans
        stream.settle()
        time.sleep(0.5)  # the diagnostics after the last answer
        diagnostics = diag_values(h.status(after=time.monotonic()))
        with h.lock:
            poses = {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in h.poses}
            aligned = {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in h.aligned}
            stream.children = {m.child_frame_id for m in h.transforms}
        statuses = stream.statuses()
        messages = len(held["statuses"])
    stream.run = Run(stream.sent, messages, statuses, poses, aligned, diagnostics, log_path.read_text())


@pytest.fixture(scope="module")
def run(ros_namespace, campus, tmp_path_factory) -> Run:
    """The node on the campus map and the whole stream, once; what it answered. The scans are cast while the
    node starts."""
    world, map_path = campus
    params = {**PARAMS, "target_file": str(map_path), "target_frame": MAP_FRAME_ID}
    with lidar_node(ros_namespace, "lidar_map", params, tmp_path_factory, lambda: phase_scans(world)) as (stream, scans):
        # standing at the start until placed without a guess and tracked twice (the map's first use)
        stream.stand(scans["start"], "start", lambda: stream.registered("start", "tracking") >= 2, 60.0)
        stream.drive(scans["drive"], "drive")
        # kidnapped: standing far away, turned, until placed again and tracked twice
        stream.stand(scans["kidnap"], "kidnap", lambda: stream.registered("kidnap", "tracking") >= 2, 30.0)
        stream.drive(scans["drive_on"], "drive_on")
        stream.settle()
        response = stream.h.call(Trigger, "relocalize")
        assert response.success, response.message
        terrace = lambda: sum("localization" in stream.statuses().get(s.key, {}) for s in stream.sent
                              if s.phase == "terrace")
        stream.stand(scans["terrace"], "terrace", lambda: terrace() >= 2, 20.0)
        maps: list[PointCloud2] = []  # subscribed only now: the node published the map long before
        stream.h.helper.create_subscription(PointCloud2, "map_cloud", stream.h._rec(maps), QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        stream.h.wait(lambda: maps, 20.0, "the latched map_cloud")
    return dataclasses.replace(stream.run, map_cloud=maps[0])


def answered(run: Run, phase: str) -> list[tuple[Sent, dict[str, str]]]:
    """The phase's scans the node registered (not superseded), in the order sent, with their statuses."""
    return [(s, run.statuses[s.key]) for s in run.sent
            if s.phase == phase and "localization" in run.statuses.get(s.key, {})]


def pose_error(run: Run, sent: Sent) -> tuple[float, float]:
    """(RE deg, TE m) of the pose published for a scan against its truth."""
    return errors(msg_to_matrix(run.poses[sent.key].pose), sent.truth)


def right(run: Run, sent: Sent) -> bool:
    re_, te = pose_error(run, sent)
    return re_ < MAX_RE and te < MAX_TE


# --------------------------------------------------------------------------- the checks
def test_one_status_per_scan_received_and_superseded_scans_counted(run):
    """Every scan the node received is answered by exactly one registration_status: registered (published
    or rejected) or superseded, as /diagnostics counts them; nothing fails otherwise. (Scans that arrive
    while the node's process is busy preparing the map beyond the subscription's depth are dropped by the
    middleware before the node sees them: received.source may be below the scans sent.)"""
    d = run.diagnostics
    received = int(d["received.source"])
    assert run.messages == len(run.statuses) == received, (run.messages, len(run.statuses), d)
    assert {s.key for s in run.sent} >= set(run.statuses) and 0 < received <= len(run.sent), d
    reasons = [v.get("reason", "") for v in run.statuses.values()]
    assert set(reasons) <= {"", "dropped.superseded", "failed.low_confidence_rejected"}, set(reasons)
    superseded = reasons.count("dropped.superseded")
    assert int(d.get("dropped.superseded", 0)) == int(d["dropped"]) == superseded, d
    assert int(d["registered"]) == sum(v.get("published") == "true" for v in run.statuses.values()), d
    assert int(d["failed"]) == int(d.get("failed.low_confidence_rejected", 0)) == reasons.count(
        "failed.low_confidence_rejected"), d
    assert int(d["registered"]) + int(d["failed"]) + int(d["dropped"]) == received, d
    assert int(d["lost.source"]) == 0 and "Traceback" not in run.log, d


def test_no_published_pose_is_wrong(run):
    """Whatever the node publishes, at any time, is within 2 deg / 25 cm of the truth; every published pose
    is announced by its status."""
    assert run.poses, "no pose published"
    wrong = []
    for sent in run.sent:
        published = run.statuses.get(sent.key, {}).get("published") == "true"
        assert published == (sent.key in run.poses), (sent, run.statuses.get(sent.key))
        if published and not right(run, sent):
            wrong.append((sent.phase, *np.round(pose_error(run, sent), 3), run.statuses[sent.key]["message"]))
    assert not wrong, wrong


def test_aligned_clouds_keep_the_drivers_fields(run):
    """A published scan's aligned cloud: its finite points (the misses, NaN, dropped) moved by the published
    pose, in the map frame, with intensity, ring and time carried unchanged in the driver's 22-byte layout."""
    layout = [(name, DRIVER_POINT.fields[name][1]) for name in DRIVER_POINT.names]
    checked = 0
    for sent in run.sent:
        msg = run.aligned.get(sent.key)
        if msg is None:
            continue
        assert msg.header.frame_id == MAP_FRAME_ID and msg.point_step == DRIVER_POINT.itemsize
        assert [(f.name, f.offset) for f in msg.fields] == layout
        kept = sent.scan.records[np.isfinite(sent.scan.records["x"])]
        out = read_points(msg)
        assert out.num_input == len(kept) < len(sent.scan.records) and out.mask is None
        records = out.records.view(DRIVER_POINT).reshape(-1)
        for name in ("intensity", "ring", "time"):
            np.testing.assert_array_equal(records[name], kept[name])
        xyz = np.c_[kept["x"], kept["y"], kept["z"]].astype(np.float64)
        np.testing.assert_allclose(out.points, apply(msg_to_matrix(run.poses[sent.key].pose), xyz), atol=1e-3)
        checked += 1
    assert checked >= 5, f"only {checked} aligned clouds received"


def test_first_scan_is_placed_without_a_guess(run):
    first, status = answered(run, "start")[0]
    assert first.key == run.sent[0].key  # the node took the first scan at once
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    assert status["published"] == "true" and right(run, first), (pose_error(run, first), status)
    assert float(status["confidence"]) >= 0.5 and status["target_frame"] == MAP_FRAME_ID
    assert status["source_frame"] == LIDAR and status["jumped"] == "true"  # not tracked from a start


def test_the_drive_is_tracked(run):
    """A placement tells no velocity: the scan taken after the first is placed again without a guess (the
    profile's map.predict_motion); from then on every scan taken is tracked from the last pose moved on at the
    last two poses' velocity, and published right."""
    later = answered(run, "start")[1:] + answered(run, "drive")
    drive = answered(run, "drive")
    assert len(drive) >= 2, f"only {len(drive)} of the drive's {sum(s.phase == 'drive' for s in run.sent)} scans taken"
    (sent, status), later = later[0], later[1:]
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    assert status["published"] == "true" and right(run, sent) and status["jumped"] == "true", status
    for sent, status in later:
        assert status["localization"] == "tracking" and status["initial_guess"] in TRACKED, status
        assert status["published"] == "true" and right(run, sent), (sent.phase, pose_error(run, sent), status)
        assert status["jumped"] == "false", status
    assert [v["initial_guess"] for _, v in later] == ["predicted"] * len(later), later


def test_a_kidnapped_vehicle_is_placed_again(run):
    """The kidnapped vehicle's scans taken before it is placed again publish nothing (no wrong pose: checked
    above); it is placed within map.lost_after (2) + 2 scans taken (after two misses tracking is lost and
    the scan is localised without a guess) and tracked on after the scan that follows it is placed again (the
    jump is not a velocity to predict with; the two placements are). The placements say `jumped: true` and are
    counted among the diagnostics' `pose_jumps`; the tracked scans say `jumped: false`."""
    kidnap = answered(run, "kidnap")
    states = [(v["localization"], v["initial_guess"], v["published"]) for _, v in kidnap]
    placed = next((n for n, (_, v) in enumerate(kidnap) if v["published"] == "true"), None)
    assert placed is not None and placed <= 2 + 2, f"not placed within lost_after + 2 scans taken: {states}"
    sent, status = kidnap[placed]
    assert right(run, sent), (pose_error(run, sent), status)
    # a jump: found by the place index, not tracked from its start; counted with the first placement's
    assert status["jumped"] == "true" and int(run.diagnostics["pose_jumps"]) >= 2, (status, run.diagnostics)
    if placed >= 2:  # lost: localised without a guess
        assert status["localization"] == "global" and status["initial_guess"] == "none", states
        assert int(run.diagnostics["tracking_lost"]) >= 1, run.diagnostics
    after = kidnap[placed + 1:] + answered(run, "drive_on")
    # the jump to the placed pose is no motion to go on with: the next scan is placed again, without a guess
    (sent, status), after = after[0], after[1:]
    assert status["initial_guess"] == "none" and status["published"] == "true" and right(run, sent), status
    for sent, status in after:
        assert status["localization"] == "tracking" and status["published"] == "true", status
        assert status["jumped"] == "false" and status["initial_guess"] == "predicted", status
        assert right(run, sent), (sent.phase, pose_error(run, sent), status)
    assert answered(run, "drive_on"), "no scan of the drive after the kidnap taken"


def test_published_covariances_are_valid(run):
    """Each published pose's covariance is a symmetric positive semi-definite 6x6 matrix (not 'unknown'); a
    pose with a named rival has its widest translation along the slide."""
    slides = 0
    for key, pose in run.poses.items():
        C = np.asarray(pose.pose.covariance, dtype=np.float64).reshape(6, 6)
        assert np.isfinite(C).all() and C[0, 0] >= 0.0, C  # -1 first: no estimate
        np.testing.assert_allclose(C, C.T, atol=1e-12 * max(1.0, np.abs(C).max()))
        w = np.linalg.eigvalsh(C)
        assert w.min() >= -1e-9 * max(w.max(), 1e-12), w
        for match in SLIDE.finditer(run.statuses[key]["unconstrained"]):
            u = np.array([float(v) for v in match.groups()[:3]])
            _, vecs = np.linalg.eigh(C[:3, :3])
            assert abs(vecs[:, -1] @ u) / np.linalg.norm(u) > 0.9, (u, C[:3, :3])
            slides += 1
    if not slides:
        pytest.skip("no published pose named a rival in this run: the covariance of a slide was not checked")


def test_the_map_is_latched_on_map_cloud(run, campus):
    """The map the node localises in (the file voxelised at map_voxel 0.2 m) reaches a subscriber that joined
    long after it was published: in the map frame, every published point within a voxel's diagonal of the
    file's points and every file point within one of a published point (scipy's k-d tree)."""
    _, map_path = campus
    msg = run.map_cloud
    assert msg is not None and msg.header.frame_id == MAP_FRAME_ID
    published = read_points(msg).points.astype(np.float64)
    file_points = np.asarray(o3d.io.read_point_cloud(str(map_path)).points)
    assert 0.5 * len(file_points) < len(published) <= len(file_points)
    diagonal = 0.2 * np.sqrt(3.0)
    assert cKDTree(file_points).query(published)[0].max() < diagonal
    assert cKDTree(published).query(file_points)[0].max() < diagonal


def test_a_slide_along_the_terraced_street_is_named(run, campus):
    """Placed without a guess in the terraced street, a scan fits the map as well shifted by whole houses:
    its status names the slide (along the street, a multiple of the houses' width), is degenerate, and
    no wrong pose is published (checked above)."""
    world, _ = campus
    terrace = answered(run, "terrace")
    assert len(terrace) >= 2, terrace
    u_street = np.r_[np.diff(world.terrace, axis=0)[0], 0.0]
    u_street /= np.linalg.norm(u_street)
    for sent, status in terrace:
        assert status["localization"] in ("global", "lost") and status["initial_guess"] == "none", status
        slides = [m.groups() for m in SLIDE.finditer(status["unconstrained"])]
        assert slides and status["degenerate"] == "true", status
        assert "rival pose" in status["message"], status
        for *u, d in slides:
            u = np.array([float(v) for v in u])
            assert abs(u @ u_street) > 0.95, (u, status)
            k = float(d) / world.terrace_period
            assert k >= 0.9 and abs(k - round(k)) < 0.1, (d, status)


# --------------------------------------------------------------------------- a tilted sensor on a robot base
BASE = "base_link"
MOUNT = sensor_pose(0.4, 0.1, HEIGHT, 0.05, np.radians(20.0), np.radians(4.0))  # T_base_sensor: pitched down 20 deg


@pytest.fixture(scope="module")
def tilted(ros_namespace, campus, tmp_path_factory) -> Run:
    """The node with `base_frame` and `base_T_source` (a LiDAR mounted 1.8 m above the base, 0.4 m forward,
    pitched down 20 deg and rolled 4 deg); the vehicle stands on the southern street until placed and drives
    on. The truth of each scan is the base's pose (on the ground); the scans are cast from the sensor's."""
    world, map_path = campus
    quaternion = Rotation.from_matrix(MOUNT[:3, :3]).as_quat()
    params = {**PARAMS, "target_file": str(map_path), "target_frame": MAP_FRAME_ID, "base_frame": BASE,
              "base_T_source": "[" + ", ".join(f"{v:.9f}" for v in (*MOUNT[:3, 3], *quaternion)) + "]"}
    south = street_poses(world)["south"]

    def on_ground(x: float) -> np.ndarray:  # T_map_base: the base on the road under where the level sensor was
        T = south(x).copy()
        T[2, 3] = 0.0
        return T

    bases = {"start": [on_ground(6.0)] * 2, "drive": [on_ground(7.0 + SPEED * k) for k in range(6)]}

    def cast() -> dict[str, list[Scan]]:
        return {phase: [Scan(driver_records(world, T @ MOUNT, seed=500 + 10 * n + k), T) for k, T in enumerate(Ts)]
                for n, (phase, Ts) in enumerate(bases.items())}

    with lidar_node(ros_namespace, "lidar_tilted", params, tmp_path_factory, cast) as (stream, scans):
        stream.stand(scans["start"], "start", lambda: stream.registered("start", "tracking") >= 2, 60.0)
        stream.drive(scans["drive"], "drive")
    assert stream.children == {BASE}, stream.children
    return stream.run


def test_a_tilted_sensor_localises_its_base(tilted):
    """With base_frame and base_T_source the node publishes the base's pose (on the ground, z up), not the
    tilted sensor's: placed without a guess and tracked, every published pose within 2 deg / 25 cm of the
    base's truth; the statuses and transforms name base_link as the child frame; the aligned cloud is the
    sensor's points moved by the published pose and the mounting (where the sensor saw them in the map)."""
    _, status = answered(tilted, "start")[0]
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    assert status["published"] == "true" and status["source_frame"] == BASE, status
    published = [s for s in tilted.sent if s.key in tilted.poses]
    assert len(published) >= 4, [tilted.statuses.get(s.key, {}).get("message") for s in tilted.sent]
    wrong = [(s.phase, *np.round(pose_error(tilted, s), 3)) for s in published if not right(tilted, s)]
    assert not wrong, wrong
    assert any(s.phase == "drive" for s in published), "no scan of the drive published"
    for sent in published:
        msg = tilted.aligned[sent.key]
        kept = sent.scan.records[np.isfinite(sent.scan.records["x"])]
        xyz = np.c_[kept["x"], kept["y"], kept["z"]].astype(np.float64)
        T_map_base = msg_to_matrix(tilted.poses[sent.key].pose)
        np.testing.assert_allclose(read_points(msg).points, apply(T_map_base @ MOUNT, xyz), atol=1e-3)
        # against the truth: the sensor's points where they are in the map, to within the pose's error
        assert np.median(np.linalg.norm(read_points(msg).points - apply(sent.truth @ MOUNT, xyz), axis=1)) < 0.25


# --------------------------------------------------------------------------- odometry (map.odometry)
ODOM = "odom"
ODOM_ERROR = sensor_pose(0.02, -0.01, 0.0, np.radians(0.3))  # the odometry's error per scan driven (drift)
TOLERANCE_NS = 200_000_000  # map.transform_tolerance's default: map -> odom stamped 0.2 s after its scan
REPEAT_S = 1.0  # map.transform_publish_period here: the last map -> odom again after 1 s without one


@pytest.fixture(scope="module")
def odometric(ros_namespace, campus, tmp_path_factory) -> tuple[Run, dict[tuple[int, int], np.ndarray], list, float]:
    """The node with map.odometry: odometry of the LiDAR (child frame velodyne) in frame odom, drifting by
    `ODOM_ERROR` per scan driven, sent at each scan's stamp just before the scan. The vehicle stands on the
    southern street until placed and tracked, then drives east speeding up (0.3 to 2.1 m per scan); then no
    scan comes for 3.5 s, the node is reset and 2.5 s pass. Returns what the node answered, the true T_map_odom
    at each scan's stamp, the odom_transform messages with their arrival (monotonic s) and the reset's time."""
    world, map_path = campus
    params = {**PARAMS, "target_file": str(map_path), "target_frame": MAP_FRAME_ID, "map.odometry": "true",
              "map.transform_publish_period": str(REPEAT_S)}
    south = street_poses(world)["south"]
    xs = 6.0 + np.cumsum(0.3 * np.arange(1, 8))
    poses = {"start": [south(6.0)] * 2, "drive": [south(x) for x in xs]}
    truth: dict[tuple[int, int], np.ndarray] = {}
    state = {"truth": poses["start"][0], "odom": np.eye(4)}

    held: dict = {"odom_tf": []}

    def also(h) -> None:
        held["odom_pub"] = h.helper.create_publisher(Odometry, "odom", QoSProfile(
            depth=50, reliability=ReliabilityPolicy.RELIABLE))
        def arrived(msg: TransformStamped) -> None:
            with h.lock:
                held["odom_tf"].append((time.monotonic(), msg))
        h.helper.create_subscription(TransformStamped, "odom_transform", arrived,
                                     QoSProfile(depth=STATUS_DEPTH, reliability=ReliabilityPolicy.RELIABLE))

    def send_odometry(header, scan: Scan) -> None:
        moved = np.linalg.inv(state["truth"]) @ scan.truth
        drift = ODOM_ERROR if np.linalg.norm(moved[:3, 3]) > 1e-6 else np.eye(4)
        state["truth"], state["odom"] = scan.truth, state["odom"] @ moved @ drift
        truth[(header.stamp.sec, header.stamp.nanosec)] = scan.truth @ np.linalg.inv(state["odom"])
        msg = Odometry(header=Header(stamp=header.stamp, frame_id=ODOM), child_frame_id=LIDAR)
        (msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z) = state["odom"][:3, 3]
        (msg.pose.pose.orientation.x, msg.pose.pose.orientation.y, msg.pose.pose.orientation.z,
         msg.pose.pose.orientation.w) = Rotation.from_matrix(state["odom"][:3, :3]).as_quat()
        held["odom_pub"].publish(msg)

    def cast() -> dict[str, list[Scan]]:
        return {phase: [Scan(driver_records(world, T, seed=700 + 10 * n + k), T) for k, T in enumerate(Ts)]
                for n, (phase, Ts) in enumerate(poses.items())}

    with lidar_node(ros_namespace, "lidar_odometry", params, tmp_path_factory, cast, also) as (stream, scans):
        wait_subscribed(stream.h, held["odom_pub"])
        stream.odometry = send_odometry
        stream.stand(scans["start"], "start", lambda: stream.registered("start", "tracking") >= 2, 60.0)
        stream.drive(scans["drive"], "drive")
        stream.settle()
        time.sleep(3.5)  # no scan: the last map -> odom is repeated
        response = stream.h.call(Trigger, "reset")
        assert response.success, response.message
        reset_at = time.monotonic()
        time.sleep(2.5)  # reset: no more repeats
    with stream.h.lock:
        odom_tf = list(held["odom_tf"])
    return stream.run, truth, odom_tf, reset_at


def test_odometry_moves_the_tracked_pose_and_gives_map_to_odom(odometric):
    """With map.odometry the scan after the placement is tracked from it moved by the odometry (no second
    placement: initial_guess odometry, jumped false), and so is every later one while the vehicle speeds up;
    every published pose is right, and each comes with the map -> odom transform of its stamp (odom_transform:
    parent map, child odom, stamped transform_tolerance later), within 2 deg / 25 cm of the drifting odometry's
    true frame."""
    run, truth, odom_tf, _ = odometric
    start = answered(run, "start")
    (first, status), later = start[0], start[1:] + answered(run, "drive")
    assert status["localization"] == "global" and status["initial_guess"] == "none", status
    assert status["published"] == "true" and right(run, first), (pose_error(run, first), status)
    assert len(answered(run, "drive")) >= 4, [v.get("message") for v in run.statuses.values()]
    for sent, status in later:
        assert status["localization"] == "tracking" and status["initial_guess"] == "odometry", status
        assert status["published"] == "true" and status["jumped"] == "false", status
        assert right(run, sent), (sent.phase, pose_error(run, sent), status)
    published = {s.key for s in run.sent if s.key in run.poses}
    by_stamp = {divmod(stamp_ns(m.header) - TOLERANCE_NS, 1_000_000_000): m for _, m in odom_tf}
    assert published <= set(by_stamp), (sorted(by_stamp), sorted(published))
    by_stamp = {k: m for k, m in by_stamp.items() if k in published}
    for key, msg in by_stamp.items():
        assert (msg.header.frame_id, msg.child_frame_id) == (MAP_FRAME_ID, ODOM), msg
        re_, te = errors(msg_to_matrix(msg), truth[key])
        assert re_ < MAX_RE and te < MAX_TE, (key, re_, te)
    drifted = [np.linalg.norm(truth[k][:3, 3] - truth[min(truth)][:3, 3]) for k in by_stamp]
    assert max(drifted) > 0.05  # the odometry frame drifted in the map: the transform followed it


def test_the_last_map_to_odom_is_repeated_while_no_pose_comes_until_a_reset(odometric):
    """With no scan for 3.5 s the last map -> odom is published again every transform_publish_period (1 s), the
    same transform stamped on by the time since it was sent (tf lookups go on between scans), stamps growing;
    after the reset service none comes."""
    run, _, odom_tf, reset_at = odometric
    published = {s.key for s in run.sent if s.key in run.poses}
    last_key = max(published)
    fresh = [k for k, (_, m) in enumerate(odom_tf) if stamp_ns(m.header) == 10**9 * last_key[0] + last_key[1]
             + TOLERANCE_NS]
    assert len(fresh) == 1, "the last pose's map -> odom"
    (sent_at, last), repeats = odom_tf[fresh[0]], odom_tf[fresh[0] + 1:]
    before = [(t, m) for t, m in repeats if t < reset_at]
    assert 2 <= len(before) <= 4, [t - sent_at for t, _ in repeats]  # 3.5 s without a pose, one a second
    previous_t, previous_ns = sent_at, stamp_ns(last.header)
    for t, m in before:
        assert (m.header.frame_id, m.child_frame_id, m.transform) == (last.header.frame_id, last.child_frame_id,
                                                                      last.transform)
        assert REPEAT_S - 0.05 < t - previous_t < REPEAT_S + 0.6, t - previous_t
        assert abs(1e-9 * (stamp_ns(m.header) - previous_ns) - (t - previous_t)) < 0.25  # stamped on by the time
        previous_t, previous_ns = t, stamp_ns(m.header)
    assert not [t for t, _ in repeats if t > reset_at + 0.3], "repeated after the reset"
