#!/usr/bin/env python3
"""register_node in a large LiDAR map, fed at 10 Hz: map mode through DDS, scan by scan, against the true poses.

    python scripts/bench_lidar_node.py [--seed 7] [--drive-scans 200] [--walk-scans 150] [--odometry] [--json PATH]
                                       [--plot PNG]

The node runs in its own process (as with `ros2 run`) with config/genreg_lidar_map.yaml as shipped (and
`diagnostics.period` 1 s). Its map is `bench_lidar_map.py`'s campus of that seed (held out: 7 and up; 4 x 3
blocks, about 9 M points fused from survey scans every 3 m at 0.1 m voxels, cached under cache/lidar_world;
--indoor-spacing: the corridors surveyed every so many metres instead),
written once as a binary PCD `target_file` under --work, where the node also keeps its prepared map
(`<file>.genreg-cache/`: the first run builds it, later runs load it). This process publishes scans in the
sensor frame as a driver does (`LidarScan.records`: x y z intensity ring time, misses as NaN), best effort
with depth 5 (SensorDataQoS), stamped 100 ms apart and sent at that pace, in four phases:
  start    standing on the longest street (bench_lidar_map's drive start; five revolutions sent in turn) until
           the node has placed the vehicle without a guess and tracked it twice (at most --stand-timeout s);
           not with --moving-start, where the node first sees the vehicle driving (started, or lost, on the way)
  drive    along that street at 10 m/s (1 m a scan; --drive-step 2: 20 m/s), --drive-scans HDL-64-like
           revolutions (~100k points)
  misclick (with --misclick) standing at the drive's end, an `initialpose` 500 m off the map is sent (an RViz
           click in the wrong place) and the vehicle stands on until tracked twice after it
  kidnap   the robot carried to the start of the building's main corridor (a floor robot, 0.6 m high,
           VLP-32-like); an operator gives its pose there (an `initialpose` 0.3 m and 5 deg off the truth: a click
           in RViz; with --click-ahead, also that far ahead along the corridor), since a scan in a corridor is not placed without a guess (`corridor_share`), and it stands
           until placed again and tracked twice
  walk     along the corridor at 1.5 m/s (0.15 m a scan), --walk-scans of them
Every scan is cast (6 moving cars and people around it) and serialised before the node starts.
With --odometry the node runs with `map.odometry` and this process sends, just before each scan, the
nav_msgs/Odometry of the sensor (child frame velodyne, frame odom) at 50 Hz since the last scan (`ODOM_AT`:
stamped 7, 27, ..., 87 ms after it, so the newest is 13 ms older than the scan and the node interpolates and
extrapolates): the true motion since the last scan (screw-interpolated) with the errors of wheel odometry
(`ODOM_SCALE` long, `ODOM_YAW_DEG_PER_M` of heading per metre), and none across the kidnap (the robot carried:
its wheels do not turn), so the odometry frame drifts in the map.

Accounting, per phase: a scan sent is answered (one registration_status for it, superseded ones included) or
lost (none came: dropped before the node took it, which its diagnostics count as missed); of the
answered, published or not (and why: the status's `reason`), what each registered scan started from (the
status's `initial_guess`); a published pose is wrong when it is 2 deg or
0.25 m or more off its truth, and jumped when its status says it was not tracked from its start. Figures: TE median and largest of the published poses, the share within 0.1 m,
the node's own latency (registration_status `latency_ms`: the scan's arrival in the node to its result)
median and p95, and the scans until the first publication after the kidnap. For the run: the time from
starting the node to its first diagnostics (map loaded and prepared), its CPU per scan and its resident
memory (RSS, MB) when ready and at the end; the node's own counts of scans received and missed (`missed.source`:
sent, never received, by the publisher's sequence numbers), and the latency of the first scan answered (the
first localisation after the node is ready). `--plot`: the run scan by scan (`plot_run`).

ROS isolation: genreg_ros.environment.ros_environment (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, the shipped
Fast DDS profile, a random ROS_DOMAIN_ID unless one is set).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from genreg_ros.replay.harness import Client, NodeProcess, ReplayOptions, node_counters, restamp, ros_env

ros_env()  # before the first DDS participant of this process

import numpy as np
import open3d as o3d
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_lidar_map import (
    HELD_OUT_SEED,
    SCAN_SENSOR,
    TRACK_SENSOR,
    code_state,
    drive_poses,
    load_text,
    placed,
    rng_of,
    walk_poses,
)
from bench_node import cpu_seconds, rss_mb

from genreg_core.data import lidar_world as lw
from genreg_core.geometry import extrapolate, make_transform
from genreg_core.metrics import transform_errors
from genreg_ros.config import CONFIG_DIR
from genreg_ros.conversions import matrix_to_pose_msg
from genreg_ros.pointcloud2 import array_to_msg

PERIOD_NS = 100_000_000  # a 10 Hz LiDAR
SENSOR_FRAME, MAP_FRAME = "velodyne", "map"
PHASES = ("start", "drive", "misclick", "kidnap", "walk")
STANDING = ("start", "misclick", "kidnap")  # phases that stand until placed and tracked twice
MISCLICK_M = 500.0  # the misclick phase's initialpose: this far east of the vehicle, m
OPERATOR_OFF = (0.3, 5.0)  # the kidnap phase's initialpose: this far (m, to the robot's left) and turned (deg)
STAND_SCANS = 5  # revolutions cast at a standing place (movers differ), sent in a new random order each round:
# the node, which takes the newest scan when it is free, does not take the same one every time (in turn, a
# search of about five scan periods took the same scan again and again)
NODE_PARAMS = {"diagnostics.period": "1.0"}  # config/genreg_lidar_map.yaml otherwise
ODOM_FRAME = "odom"
ODOM_SCALE = 1.02  # --odometry: the odometry's distances 2 % long
ODOM_YAW_DEG_PER_M = 0.2  # ... and its heading off by this much per metre driven (counter-clockwise)
ODOM_AT = (0.07, 0.27, 0.47, 0.67, 0.87)  # --odometry: its messages' stamps between two scans, in scan periods


@dataclass
class Sent:
    """A scan as published: its stamp (ns), phase, true pose T_map_sensor and when it went out (monotonic)."""

    stamp: int
    phase: str
    truth: np.ndarray
    at: float


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="the campus world's seed (held out: 7 and up)")
    p.add_argument("--drive-scans", type=int, default=200, help="scans of the drive")
    p.add_argument("--drive-step", type=int, default=1, help="m between the drive's scans (1: 10 m/s, 2: 20 m/s)")
    p.add_argument("--walk-scans", type=int, default=150, help="scans of the corridor walk, 0.15 m apart")
    p.add_argument("--misclick", action="store_true", help="an initialpose 500 m off the map after the drive")
    p.add_argument("--click-ahead", type=float, default=0.0, help="the kidnap phase's initialpose also this far ahead "
                   "of the robot along the corridor, m (a click metres off)")
    p.add_argument("--moving-start", action="store_true", help="no standing start: placed while it drives")
    p.add_argument("--odometry", action="store_true", help="the node with map.odometry, fed the sensor's odometry")
    p.add_argument("--laps", type=int, default=1, help="the four phases this many times (a soak: is RSS flat?)")
    p.add_argument("--stand-timeout", type=float, default=30.0, help="longest stand at the start and the kidnap, s")
    p.add_argument("--startup-timeout", type=float, default=600.0, help="longest wait for the node's map, s")
    p.add_argument("--work", default="runs/bench_lidar_node", help="where the map file and the node's log go")
    p.add_argument("--cache-dir", default="cache/lidar_world", help="where world maps are kept")
    p.add_argument("--indoor-spacing", type=float, default=None, help="m between the map survey's scans in "
                   "corridors (default: every 3 m, as on roads)")
    p.add_argument("--json", default=None, help="also write the figures and every scan's status here")
    p.add_argument("--plot", default=None, help="also draw the run scan by scan (latency, TE) into this PNG")
    return p.parse_args(argv)


def map_file(world: lw.World, cache_dir: str, work: Path, indoor_spacing: float | None = None) -> Path:
    """The world's map (`indoor_spacing`: of the corridors' survey) as a binary PCD under `work` (written once)."""
    path = work / f"{world.key}{'' if indoor_spacing is None else f'-in{indoor_spacing:g}'}.pcd"
    if not path.exists():
        points = lw.cached_map(world, cache_dir=cache_dir, indoor_spacing=indoor_spacing)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
        work.mkdir(parents=True, exist_ok=True)
        if not o3d.io.write_point_cloud(str(path), cloud):
            raise SystemExit(f"could not write {path}")
    return path


def serialised(world: lw.World, poses: np.ndarray, rng: np.random.Generator, sensor, desc: str) -> list[bytes]:
    """Each pose's revolution (misses kept, as NaN) as a serialised PointCloud2 in the sensor frame."""
    out = []
    sensor = dataclasses.replace(sensor, keep_misses=True)
    for T in tqdm(poses, desc=f"casting {desc}", unit="scan", leave=False):
        header = Header(frame_id=SENSOR_FRAME)
        out.append(serialize_message(array_to_msg(header, lw.world_scan(world, T, rng, sensor).records(),
                                                  is_dense=False)))
    return out


class Stream:
    """Scans published at 10 Hz, stamped 100 ms apart; the node's answers read back by stamp."""

    def __init__(self, client: Client, odometry=None) -> None:
        """`odometry`: a nav_msgs/Odometry publisher (--odometry), else None."""
        self.client, self.sent = client, list[Sent]()
        self.stamp = time.time_ns() // PERIOD_NS * PERIOD_NS
        self.next_at = time.monotonic()
        self.odometry, self.odom = odometry, np.eye(4)  # T_odom_sensor, integrated from the true motion
        self.rng = np.random.default_rng(0)  # the order of standing scans (`stand`)

    def publish(self, raw: bytes, truth: np.ndarray, phase: str) -> None:
        time.sleep(max(0.0, self.next_at - time.monotonic()))
        self.next_at = max(self.next_at + PERIOD_NS / 1e9, time.monotonic())
        if self.odometry is not None:
            for msg in self.odometry_msgs(truth, phase):
                self.odometry.publish(msg)
        self.client.pub_source.publish(restamp(raw, self.stamp))
        self.sent.append(Sent(self.stamp, phase, truth, time.monotonic()))
        self.stamp += PERIOD_NS

    def odometry_msgs(self, truth: np.ndarray, phase: str) -> list[Odometry]:
        """The odometry since the last scan (`ODOM_AT`), before this one: the last scan's moved by the true
        motion to this one with wheel odometry's errors (none before the first scan, or into the kidnap or a lap's
        start: carried there), screw-interpolated."""
        before = self.odom
        if self.sent and not (phase in ("start", "kidnap") and self.sent[-1].phase != phase):
            moved = np.linalg.inv(self.sent[-1].truth) @ truth
            metres = float(np.linalg.norm(moved[:3, 3]))
            moved[:3, 3] *= ODOM_SCALE
            self.odom = before @ moved @ make_transform(
                Rotation.from_euler("z", ODOM_YAW_DEG_PER_M * metres, degrees=True).as_matrix(), np.zeros(3))
        out = []
        for f in ODOM_AT:
            sec, nanosec = divmod(self.stamp - PERIOD_NS + round(f * PERIOD_NS), 1_000_000_000)
            msg = Odometry(header=Header(frame_id=ODOM_FRAME), child_frame_id=SENSOR_FRAME)
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
            msg.pose = matrix_to_pose_msg(extrapolate(before, self.odom, f - 1.0), msg.header, None).pose
            out.append(msg)
        return out

    def tracked(self, since: int) -> int:
        """The scans sent from the `since`-th on published in state tracking so far."""
        with self.client.lock:
            status = dict(self.client.status)
        return sum(status.get(s.stamp, {}).get("published") == "true" and
                   status[s.stamp].get("localization") == "tracking" for s in self.sent[since:])

    def stand(self, raws: list[bytes], truths: np.ndarray, phase: str, timeout: float) -> None:
        """Publish the phase's scans, each round in a new order (`STAND_SCANS`), until two are published in state
        tracking, or `timeout` s."""
        deadline, k, since = time.monotonic() + timeout, 0, len(self.sent)
        order = np.arange(len(raws))
        while self.tracked(since) < 2 and time.monotonic() < deadline:
            if k % len(raws) == 0:
                order = self.rng.permutation(len(raws))
            i = order[k % len(raws)]
            self.publish(raws[i], truths[i], phase)
            k += 1

    def drive(self, raws: list[bytes], truths: np.ndarray, phase: str) -> None:
        for raw, T in zip(raws, truths, strict=True):
            self.publish(raw, T, phase)

    def settle(self, timeout: float = 30.0) -> None:
        """Wait until every scan sent is answered, or `timeout` s after the last answer."""
        last, count = time.monotonic(), -1
        while time.monotonic() - last < timeout:
            with self.client.lock:
                answered = sum(s.stamp in self.client.status for s in self.sent)
            if answered == len(self.sent):
                return
            if answered != count:
                last, count = time.monotonic(), answered
            time.sleep(0.1)


@dataclass(frozen=True)
class Answer:
    """One scan sent and what came of it: its status values ({} when none came: lost), and, when published,
    the published pose's errors against the truth (RE deg, TE m)."""

    sent: Sent
    status: dict[str, str]
    errors: tuple[float, float] | None

    @property
    def answered(self) -> bool:
        return bool(self.status)

    @property
    def latency_ms(self) -> float | None:
        return float(self.status["latency_ms"]) if "latency_ms" in self.status else None


def answers(stream: Stream) -> list[Answer]:
    """Every scan sent, in order, with its answer: published when its status says so and its transform came."""
    client = stream.client
    with client.lock:
        status, transforms = dict(client.status), dict(client.transforms)
    out = []
    for s in stream.sent:
        values = status.get(s.stamp, {})
        published = values.get("published") == "true" and s.stamp in transforms
        out.append(Answer(s, values, tuple(transform_errors(transforms[s.stamp].T, s.truth)) if published else None))
    return out


def scan_record(a: Answer) -> dict[str, object]:
    """One scan for the JSON: its stamp, phase, status values and, when published, its RE (deg) and TE (m)."""
    return {"stamp": a.sent.stamp, "phase": a.sent.phase, "status": a.status,
            "re_deg": None if a.errors is None else a.errors[0], "te_m": None if a.errors is None else a.errors[1]}


def phase_figures(run: list[Answer], phase: str) -> dict[str, object]:
    """The accounting and figures of one phase's scans of the run's `answers` (see the module's docstring)."""
    sent = [a for a in run if a.sent.phase == phase]
    answered = [a for a in sent if a.answered]
    published = [a for a in answered if a.errors is not None]
    te = np.array([a.errors[1] for a in published])
    latency = np.array([a.latency_ms for a in answered if a.latency_ms is not None])
    first = next((k for k, a in enumerate(sent) if a.errors is not None), None)
    return {
        "sent": len(sent), "answered": len(answered), "lost": len(sent) - len(answered),
        "published": len(published), "wrong": sum(not placed(*a.errors) for a in published),
        "jumped": sum(a.status.get("jumped") == "true" for a in published),
        "reasons": dict(Counter(a.status.get("reason", "") for a in answered
                                if a.status.get("published") != "true")),
        "states": dict(Counter(a.status.get("localization", "-") for a in answered)),
        "guesses": dict(Counter(a.status["initial_guess"] for a in answered if "initial_guess" in a.status)),
        "te_median_m": float(np.median(te)) if len(te) else float("nan"),
        "te_max_m": float(te.max()) if len(te) else float("nan"),
        "within_0.1_m": f"{int((te < 0.1).sum())}/{len(te)}",
        "latency_ms_p50": float(np.median(latency)) if len(latency) else float("nan"),
        "latency_ms_p95": float(np.percentile(latency, 95)) if len(latency) else float("nan"),
        "first_published": first,
    }


def plot_run(run: list[Answer], path: Path, title: str) -> None:
    """The run scan by scan against the time it was sent: the node's latency (above; a scan not published is
    a cross) and each published pose's TE (below, log scale; wrong ones, 2 deg or 0.25 m off, in red), the
    phases in colour, the 30 ms tracking goal and the 0.1 m line drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = run[0].sent.at if run else 0.0
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for k, phase in enumerate(dict.fromkeys(a.sent.phase for a in run)):
        colour = f"C{k}"
        mine = [a for a in run if a.sent.phase == phase]
        done = [a for a in mine if a.errors is not None and a.latency_ms is not None]
        held = [a for a in mine if a.errors is None and a.latency_ms is not None]
        top.scatter([a.sent.at - t0 for a in done], [a.latency_ms for a in done], s=6, color=colour, label=phase)
        top.scatter([a.sent.at - t0 for a in held], [a.latency_ms for a in held], s=14, marker="x", color=colour)
        right = [a for a in done if placed(*a.errors)]
        bottom.scatter([a.sent.at - t0 for a in right], [max(a.errors[1], 1e-4) for a in right], s=6, color=colour)
        wrong = [a for a in done if not placed(*a.errors)]
        bottom.scatter([a.sent.at - t0 for a in wrong], [a.errors[1] for a in wrong], s=14, color="red")
    top.axhline(30.0, color="grey", lw=0.8, ls="--")
    top.set_yscale("log")
    top.set_ylabel("node latency, ms")
    top.legend(loc="upper right", fontsize=8, markerscale=2)
    top.set_title(title, fontsize=10)
    bottom.axhline(0.1, color="grey", lw=0.8, ls="--")
    bottom.set_yscale("log")
    bottom.set_ylabel("TE of published poses, m")
    bottom.set_xlabel("time sent, s")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def misclick(truth: np.ndarray) -> PoseWithCovarianceStamped:
    """An `initialpose` in the map frame `MISCLICK_M` east of the vehicle's true pose, as RViz sends one."""
    T = truth.copy()
    T[0, 3] += MISCLICK_M
    return matrix_to_pose_msg(T, Header(frame_id=MAP_FRAME), None)


def operator_pose(truth: np.ndarray, ahead: float = 0.0) -> PoseWithCovarianceStamped:
    """An `initialpose` in the map frame `OPERATOR_OFF` from the robot's true pose (to its left, turned
    counter-clockwise) and `ahead` m along its heading (along the corridor), as an operator's click in RViz gives it."""
    metres, degrees = OPERATOR_OFF
    T = truth @ make_transform(Rotation.from_euler("z", degrees, degrees=True).as_matrix(), np.array([ahead, metres, 0.0]))
    return matrix_to_pose_msg(T, Header(frame_id=MAP_FRAME), None)


def wait_ready(client: Client, node: NodeProcess, timeout: float) -> float:
    """Seconds until the node's first diagnostics and a matched scan publisher (its map prepared)."""
    t0 = time.monotonic()
    while not (client.latest_diagnostics() and client.pub_source.get_subscription_count() > 0
               and client.sub_tf.get_publisher_count() > 0):
        if not node.alive():
            raise SystemExit(f"the node exited: {node.error_line()}")
        if time.monotonic() - t0 > timeout:
            raise SystemExit(f"the node was not ready within {timeout:.0f} s: {node.error_line()}")
        time.sleep(0.2)
    return time.monotonic() - t0


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    work = Path(args.work)
    world = lw.campus_world(args.seed, (4, 3))
    path = map_file(world, args.cache_dir, work, args.indoor_spacing)
    drive = drive_poses(world, args.drive_scans * args.drive_step)[::args.drive_step]
    walk = walk_poses(world, args.walk_scans)
    poses = {"start": drive[:1].repeat(STAND_SCANS, 0), "drive": drive[1:], "misclick": drive[-1:].repeat(STAND_SCANS, 0),
             "kidnap": walk[:1].repeat(STAND_SCANS, 0), "walk": walk[1:]}
    sensors = {"start": TRACK_SENSOR, "drive": TRACK_SENSOR, "misclick": TRACK_SENSOR, "kidnap": SCAN_SENSOR,
               "walk": SCAN_SENSOR}
    phases = [p for p in PHASES if (p != "misclick" or args.misclick) and (p != "start" or not args.moving_start)]
    raws = {phase: serialised(world, poses[phase], rng_of("walk-indoor" if sensors[phase] is SCAN_SENSOR else "track",
                                                          args.seed, 100 + k), sensors[phase], phase)
            for k, phase in enumerate(PHASES) if phase in phases}
    print(f"# register_node in a LiDAR map at 10 Hz ({world.key}, {path.stat().st_size / 1e6:.0f} MB map file)")
    print(f"code: {code_state()}; 2 cores, OMP_NUM_THREADS {os.environ.get('OMP_NUM_THREADS', '-')}; "
          f"load average at start {load_text()}; ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}")
    options = ReplayOptions(params_file=CONFIG_DIR / "genreg_lidar_map.yaml",
                            node_params={**NODE_PARAMS, "target_file": str(path.resolve()), "target_frame": MAP_FRAME,
                                         **({"map.odometry": "true"} if args.odometry else {})})
    node = NodeProcess(options, work / "node.log")
    client = Client("", input_reliability="best_effort", input_depth=5, aligned=False, status=True)
    initialpose = client.node.create_publisher(PoseWithCovarianceStamped, "/initialpose", 1)
    odometry = client.node.create_publisher(Odometry, "odom", QoSProfile(
        depth=50, reliability=ReliabilityPolicy.RELIABLE)) if args.odometry else None
    try:
        ready_s = wait_ready(client, node, args.startup_timeout)
        time.sleep(1.0)  # discovery settles
        rss_ready, cpu0 = rss_mb(node.proc.pid), cpu_seconds(node.proc.pid)
        stream = Stream(client, odometry)
        t0, rss_laps = time.monotonic(), []
        for _ in range(args.laps):
            for phase in phases:
                if phase in ("misclick", "kidnap"):  # after the last answer, so that a scan of this phase takes it
                    stream.settle(5.0)
                    truth = poses[phase][0]
                    initialpose.publish(misclick(truth) if phase == "misclick" else operator_pose(truth, args.click_ahead))
                    time.sleep(0.2)
                if phase in STANDING:
                    stream.stand(raws[phase], poses[phase], phase, args.stand_timeout)
                else:
                    stream.drive(raws[phase], poses[phase], phase)
            rss_laps.append(rss_mb(node.proc.pid))
        stream.settle()
        wall = time.monotonic() - t0
        cpu = cpu_seconds(node.proc.pid) - cpu0
        rss_end = rss_mb(node.proc.pid)
        run = answers(stream)
        figures = {phase: phase_figures(run, phase) for phase in phases}
        time.sleep(1.5)  # the node's diagnostics after the last scan
        counts = node_counters(client.latest_diagnostics() or {})
    finally:
        client.close()
        code = node.stop()
    sent = sum(f["sent"] for f in figures.values())
    print(f"node ready (map read, prepared) {ready_s:.1f} s after start; {sent} scans in {wall:.1f} s ({args.laps} "
          f"lap(s)); node CPU {1e3 * cpu / max(sent, 1):.0f} ms a scan ({cpu / wall:.2f} cores); RSS {rss_ready:.0f} MB "
          f"ready, after each lap {', '.join(f'{r:.0f}' for r in rss_laps)} MB, {rss_end:.0f} MB at the end; load "
          f"average at end {load_text()}; node exit code {code}")
    first = next((a for a in run if a.latency_ms is not None), None)
    if first is not None:
        print(f"the first scan answered (placed without a guess, or not) in {first.latency_ms:.0f} ms")
    print(f"the node's counts: received {counts.get('received.source', 0)} scans, missed "
          f"{counts.get('missed.source', 0)} (sent, never received), lost {counts.get('lost.source', 0)} (reported by "
          f"the middleware), of {sent} sent")
    print()
    print("| phase | sent | answered | lost | published | wrong | jumped | not published: reasons | states | "
          "started from | TE median / max m | TE < 0.1 m | latency p50 / p95 ms | first published |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for phase, f in figures.items():
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(f["reasons"].items())) or "-"
        states = ", ".join(f"{k} {v}" for k, v in sorted(f["states"].items()))
        guesses = ", ".join(f"{k} {v}" for k, v in sorted(f["guesses"].items()))
        print(f"| {phase} | {f['sent']} | {f['answered']} | {f['lost']} | {f['published']} | {f['wrong']} | {f['jumped']} | "
              f"{reasons} | "
              f"{states} | {guesses} | {f['te_median_m']:.3f} / {f['te_max_m']:.3f} | {f['within_0.1_m']} | "
              f"{f['latency_ms_p50']:.0f} / {f['latency_ms_p95']:.0f} | {f['first_published']} |")
    if args.plot:
        plot_run(run, Path(args.plot), f"register_node in {world.key} at 10 Hz: {args.laps} lap(s), {sent} scans\n"
                 f"{code_state()}")
        print(f"wrote {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps({"world": world.key, "ready_s": ready_s, "wall_s": wall, "cpu_s": cpu,
                                               "rss_ready_mb": rss_ready, "rss_laps_mb": rss_laps,
                                               "rss_end_mb": rss_end, "node_counts": counts, "phases": figures,
                                               "first_latency_ms": None if first is None else first.latency_ms,
                                               "scans": [scan_record(a) for a in run]},
                                              indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
