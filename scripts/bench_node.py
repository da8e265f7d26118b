#!/usr/bin/env python3
"""register_node benchmarks on 300k-point clouds: node overhead, and a 30 Hz soak.

    python scripts/bench_node.py overhead [--points 300000] [--pairs 30]
    python scripts/bench_node.py soak [--rate 30] [--duration 60] [--clouds redkitchen] [--json PATH]

overhead: the node runs in this process; pairs are sent one at a time and the node's own per-pair
  timings are read back. Overhead = the two subscription callbacks (checks + pairing) + decoding both
  clouds + transforming and encoding the aligned cloud + publishing, i.e. everything on top of
  preprocessing and registration. Goal: median <= 15 ms.
soak: the node runs in its own process (as with `ros2 run`) with the params file config/genreg.yaml (the
  scene model `7scenes`, GICP refinement; sync.slop 1 ms as in the replay harness, so a lost cloud is never
  paired with a neighbour's) and the shipped Fast DDS profile; this process publishes source/target pairs
  at --rate for --duration seconds (best effort, like a sensor) and prints the node's counters and
  resident memory (RSS) every 5 s, then one summary block (and --json PATH). The node's 30 Hz goals (since
  commit c55fa3c, 2026-12-01; raised 2026-12-04): >= 28 registered pairs per second, p95 latency <= 75 ms, RSS flat.
  Clouds (--clouds): `redkitchen` (default; any shipped sequence name works): the full-resolution frames
  --start .. --start + --count - 1 (7-Scenes redkitchen validation frames 800-999, pixel stride 1, x y z
  rgb as genreg_ros.bag.make_bag writes them, ~272k points, 4.4 MB each); pair k = (target frame k - gap,
  source frame k), gap 1, looped over for the whole duration. A bag folder (genreg-make-bag output): its
  clouds, paired the same way. `synthetic`: the same 300k-point box pair (--points) again and again. `campus`:
  LiDAR scans 1 m apart along a street of a synthetic campus (--campus-seed: 7, held out, by default; about 136k
  points; --count scans), for a LiDAR params file at 10 Hz (--params-file config/genreg_lidar.yaml --rate 10); the rate goal
  is then the same share of --rate (28 of 30).
  Every message is serialised before the timed loop; each pair goes out with one fresh stamp (wall
  clock) on both clouds, target first.
  Accounting: a sent pair is registered (the node's transform with its stamp arrived) or gets the reason
  the node counted (superseded, failed.*, dropped.unmatched, ...) or "lost" (not counted by the node):
  genreg_ros.replay.scoring.assign_reasons, as in genreg-replay.
  Latency: `node` is the node's own figure per pair (latency_ms of its registration_status message): from
  the arrival of the pair's later cloud in the node to the result, before the aligned cloud is encoded and
  the transform published (the figure /diagnostics' latency_ms.median is made of). `end-to-end`: from this
  process publishing the later cloud to receiving the node's transform for it.
  CPU (after the warm-up, from /proc): the node's cores, split into its own process (taking, decoding,
  handing over and publishing the clouds) and its worker processes (the registrations), and this
  publishing process's; and the same as CPU milliseconds per registered pair (the per-pair budget).
  Accuracy: each registered pair's transform against the ground truth (RGBDSequence.relative_pose, or the
  bag's poses): RE (deg) / TE (m) medians and the share with RE < 2 deg and TE < 5 cm; the identity on the
  same pairs for scale (gap-1 motion at 30 Hz is small).

Both modes talk to the node through the replay harness's client (genreg_ros.replay.harness.Client);
overhead reads the per-pair figures from the node's /diagnostics (`last.*`, `callback_ms.median`) and its
registration_status (`latency_ms`).
The model is the params file's (`7scenes`) unless --checkpoint names another (overhead: `7scenes`).
ROS isolation: genreg_ros.environment.ros_environment (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, the
shipped Fast DDS profile, the ROS_DOMAIN_ID of the environment or a random one).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import threading
import time
from collections import Counter
from pathlib import Path

from genreg_ros.environment import ros_environment

os.environ.update(ros_environment())  # before the first DDS participant of this process

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from genreg_ros.conversions import split_ns
from genreg_ros.pointcloud2 import array_to_msg
from genreg_ros.replay.harness import (
    DEFAULT_PARAMS,
    Client,
    NodeProcess,
    ReplayOptions,
    counter_deltas,
    restamp,
    yaml_param,
)
from genreg_ros.replay.scoring import PairResult, assign_reasons, make_pairs, summarize

# The node's 30 Hz goals and the success criterion of the accuracy figures.
GOAL_RATE = 28.0  # registered pairs per second, of 30 sent (at another --rate: the same share of it)
GOAL_P95_MS = 75.0
SUCCESS_RE_DEG, SUCCESS_TE_M = 2.0, 0.05
SYNTHETIC_DEG, SYNTHETIC_T = 3.0, (0.1, 0.0, 0.0)  # the synthetic pair's motion


def make_clouds(n: int) -> tuple[PointCloud2, PointCloud2]:
    """A source (x, y, z, rgb float32) and the same scene moved by 3 degrees about z and 10 cm along x
    (`synthetic_T_gt`), in two frames."""
    rng = np.random.default_rng(0)
    dt = np.dtype({"names": ["x", "y", "z", "rgb"], "formats": ["<f4"] * 4})
    pts = rng.uniform([0, 0, 0], [20, 15, 3], size=(n, 3))
    pts[: n // 3, 2] = 0.0  # a floor
    T = synthetic_T_gt()
    moved = pts @ T[:3, :3].T + T[:3, 3]
    clouds = []
    for frame, p in (("lidar", pts), ("map", moved)):
        rec = np.zeros(n, dt)
        rec["x"], rec["y"], rec["z"] = p.T
        rec["rgb"] = rng.uniform(size=n)
        clouds.append(array_to_msg(Header(frame_id=frame), rec))
    return clouds[0], clouds[1]


def synthetic_T_gt() -> np.ndarray:
    """T_target_source of the synthetic pair: the target is the source rotated about z, then shifted."""
    c, s = np.cos(np.radians(SYNTHETIC_DEG)), np.sin(np.radians(SYNTHETIC_DEG))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = SYNTHETIC_T
    return T


def set_stamp(msg: PointCloud2, t_ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = split_ns(t_ns)


def med(values) -> float:
    return float(np.median(values)) if len(values) else float("nan")


# ----------------------------------------------------------------------------------------- overhead
def overhead(args: argparse.Namespace) -> None:
    from genreg_ros.node import RegisterNode

    ckpt = args.checkpoint or "7scenes"
    ns = f"/bench_{os.getpid()}"
    rclpy.init()
    node = RegisterNode(namespace=ns, parameter_overrides=[Parameter("model.checkpoint", value=ckpt)])
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    client = Client(ns, input_depth=2, status=True, name="bench_helper")
    try:
        wait_for_node(client, None, timeout=90.0)
        src, tgt = make_clouds(args.points)
        print(f"node overhead, {args.points} points per cloud ({len(src.data) / 1e6:.1f} MB), {args.pairs} pairs "
              "(+2 warm-up), median; goal <= 15 ms")
        figures, latency, diag = [], [], {}
        for i in range(args.pairs + 2):
            stamp = (1000 + i) * 10**9
            set_stamp(src, stamp)
            set_stamp(tgt, stamp)
            client.pub_source.publish(src)
            client.pub_target.publish(tgt)
            diag = registered_figures(client, stamp, i + 1, timeout=30.0)
            if i >= 2:  # the warm-up pairs stay out
                figures.append(diag)
                latency.append(float(client.status.get(stamp, {}).get("latency_ms", "nan")))
    finally:
        client.close()
        executor.shutdown()
        spinner.join(timeout=5)
        node.close()
        rclpy.shutdown()
    with client.lock:
        widths = {out.num_points for out in client.aligned.values()}
    assert len(client.aligned) == args.pairs + 2 and widths == {src.width} and all(figures), \
        "not every pair was registered"
    cb = 2 * float(diag["callback_ms.median"])  # all callbacks so far (the node keeps the last 200)

    def part(key: str) -> list[float]:
        return [float(d[f"last.{key}"]) for d in figures]

    parts = {k: med(part(k)) for k in ("decode_ms", "encode_ms", "publish_ms")}
    total = [cb + d + e + p for d, e, p in zip(part("decode_ms"), part("encode_ms"), part("publish_ms"), strict=True)]
    print(f"  2 callbacks (checks + pairing)   {cb:7.2f} ms")
    print(f"  decode source + target           {parts['decode_ms']:7.2f} ms")
    print(f"  transform + encode aligned cloud {parts['encode_ms']:7.2f} ms")
    print(f"  publish aligned + transform      {parts['publish_ms']:7.2f} ms")
    print(f"  overhead total (median per pair) {med(total):7.2f} ms   [{'OK' if med(total) <= 15 else 'ABOVE GOAL'}]")
    print(f"  for reference: preprocess {med(part('preprocess_ms')):.2f} ms, "
          f"registration {med(part('register_ms')):.1f} ms")
    p50, p95 = (float(np.percentile(latency, q)) for q in (50, 95))
    print(f"  node latency (later cloud's arrival -> published) p50 {p50:.1f} ms, p95 {p95:.1f} ms")


def wait_for_node(client: Client, node: NodeProcess | None, timeout: float) -> None:
    """Until the client's publishers and subscriptions match the node's and its first /diagnostics came."""
    deadline = time.monotonic() + timeout
    while not (client.matched() and client.latest_diagnostics() is not None):
        if node is not None and not node.alive():
            raise SystemExit(f"the node exited (code {node.proc.returncode}): {node.error_line()}")
        if time.monotonic() > deadline:
            where = f"; see {node.log_path}" if node is not None else ""
            raise SystemExit(f"node {client.fqn} not reachable within {timeout:.0f} s{where}")
        time.sleep(0.1)


def registered_figures(client: Client, stamp: int, registered: int, timeout: float) -> dict[str, str]:
    """Wait for the pair's transform, aligned cloud and registration_status, then for a /diagnostics status
    that counts `registered` pairs: its values (`last.*` are that pair's figures). {} on timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with client.lock:
            done = stamp in client.transforms and stamp in client.aligned and stamp in client.status
        if done:
            break
        time.sleep(0.002)
    while time.monotonic() < deadline:
        values = client.latest_diagnostics()
        if values is not None and int(values.get("registered", 0)) >= registered:
            return values
        time.sleep(0.01)
    return {}


# ----------------------------------------------------------------------------------------- soak
@dataclasses.dataclass(frozen=True)
class PairTemplate:
    """One pair of the soak's loop: the serialised clouds to publish (restamped at every send) and the pair's
    frames and ground truth (a PairResult, copied for every send and scored like a genreg-replay pair)."""

    pair: PairResult
    source_raw: bytes
    target_raw: bytes


@dataclasses.dataclass(frozen=True)
class CloudSet:
    name: str
    pairs: list[PairTemplate]
    points: float  # mean points per cloud
    megabytes: float  # mean serialised size per cloud


def _cloud_set(name: str, pairs: list[PairTemplate]) -> CloudSet:
    if not pairs:
        raise SystemExit(f"soak: no pairs in {name}")
    clouds = {id(t.source_raw): t.source_raw for t in pairs} | {id(t.target_raw): t.target_raw for t in pairs}
    sizes = [len(r) for r in clouds.values()]
    points = float(np.mean([t.pair.source_points for t in pairs]))
    return CloudSet(name, pairs, points, float(np.mean(sizes)) / 1e6)


def sequence_clouds(name: str, start: int | None, count: int | None, pixel_stride: int, gap: int) -> CloudSet:
    """Frames of a shipped RGB-D sequence as genreg-make-bag writes them (x, y, z, rgb; camera optical frame),
    serialised; pairs (target = frame k - gap, source = frame k) with T_gt = RGBDSequence.relative_pose."""
    from genreg_core.data.rgbd import RGBDSequence
    from genreg_ros.bag.make_bag import select_frames
    from genreg_ros.bag.writer import CLOUD_TYPE, DEFAULT_FRAME_ID, TYPESTORE, cloud_message, sequence_frames

    seq = RGBDSequence.open(name)
    frames = select_frames(seq.frame_indices, start, None, 1, count)
    if len(frames) <= gap:
        raise SystemExit(f"soak: {len(frames)} frames of {name} from {start} cannot make gap-{gap} pairs")
    raw, points, stamps = {}, {}, {}
    for f in sequence_frames(seq, frames, pixel_stride):
        msg = cloud_message(f.stamp_ns, DEFAULT_FRAME_ID, f.points, f.colors)
        raw[f.index] = bytes(TYPESTORE.serialize_cdr(msg, CLOUD_TYPE))
        points[f.index], stamps[f.index] = len(f.points), f.stamp_ns  # depth_to_points: finite points only
    pairs = []
    for k in range(gap, len(frames)):
        s, t = frames[k], frames[k - gap]
        pair = PairResult(seq.name, k, s, t, stamps[s], stamps[t], DEFAULT_FRAME_ID, DEFAULT_FRAME_ID, points[s],
                          seq.relative_pose(s, t))
        pairs.append(PairTemplate(pair, raw[s], raw[t]))
    return _cloud_set(f"{seq.name} frames {frames[0]}-{frames[-1]} (pixel stride {pixel_stride})", pairs)


def bag_clouds(path: Path, gap: int) -> CloudSet:
    """The clouds of a bag (genreg-make-bag), paired as genreg-replay pairs them (scoring.make_pairs)."""
    from genreg_ros.bag.reader import read_bag

    bag = read_bag(path)  # decoded once for the finite-point counts, then dropped
    pairs = [PairTemplate(p, bag.clouds[p.k].raw, bag.clouds[p.k - gap].raw) for p in make_pairs(bag, gap)
             if not p.malformed]
    frames = bag.frame_numbers
    return _cloud_set(f"bag {path} frames {frames[0]}-{frames[-1]}", pairs)


def goal_rate(rate: float) -> float:
    """The registered pairs per second a soak at `rate` pairs per second must reach (`GOAL_RATE` of 30)."""
    return GOAL_RATE * rate / 30.0


def campus_clouds(seed: int, count: int | None, gap: int) -> CloudSet:
    """Scans of the synthetic campus `seed` (`genreg_core.data.lidar_world`: 0 and 1 train, 7 is held out) 1 m apart along its
    longest street (a drive at 10 m/s seen at 10 Hz), by scripts/bench_lidar_map.py's HDL-64-like drive sensor
    (about 136k points, x y z, frame `velodyne`, 10 Hz stamps), serialised; pairs (target = scan k - gap, source =
    scan k) with T_gt from the scans' poses."""
    from bench_lidar_map import TRACK_SENSOR, drive_poses

    from genreg_core.data import lidar_world as lw
    from genreg_ros.pointcloud2 import xyz_to_msg

    world, frame = lw.campus_world(seed), "velodyne"
    poses = drive_poses(world, count or 200)
    raw, points, stamps = {}, {}, {}
    for k, pose in enumerate(poses):
        cloud = lw.world_scan(world, pose, np.random.default_rng([seed, k]), TRACK_SENSOR).points
        stamps[k] = int(1e9) + k * 100_000_000
        header = Header(frame_id=frame)
        header.stamp.sec, header.stamp.nanosec = divmod(stamps[k], 1_000_000_000)
        raw[k], points[k] = serialize_message(xyz_to_msg(header, cloud)), len(cloud)
    pairs = [PairTemplate(PairResult("campus", k, k, k - gap, stamps[k], stamps[k - gap], frame, frame, points[k],
                                     np.linalg.inv(poses[k - gap]) @ poses[k]), raw[k], raw[k - gap])
             for k in range(gap, len(poses))]
    return _cloud_set(f"synthetic campus {seed}, {len(poses)} scans 1 m apart along a street", pairs)


def synthetic_clouds(n: int) -> CloudSet:
    src, tgt = make_clouds(n)
    pair = PairResult("synthetic", 1, 1, 0, 0, 0, src.header.frame_id, tgt.header.frame_id, n, synthetic_T_gt())
    return _cloud_set(f"synthetic {n}-point boxes", [PairTemplate(pair, serialize_message(src), serialize_message(tgt))])


def load_clouds(args) -> CloudSet:
    from genreg_core.data.rgbd import SEQUENCES

    if args.clouds == "synthetic":
        return synthetic_clouds(args.points)
    if args.clouds == "campus":
        return campus_clouds(args.campus_seed, args.count, args.gap)
    if args.clouds in SEQUENCES:
        return sequence_clouds(args.clouds, args.start, args.count, args.pixel_stride, args.gap)
    if Path(args.clouds).is_dir():
        return bag_clouds(Path(args.clouds), args.gap)
    raise SystemExit(f"soak: --clouds must be synthetic, campus, a sequence ({', '.join(sorted(SEQUENCES))}) or a "
                     f"bag folder, got {args.clouds!r}")


def process_tree(pid: int) -> list[int]:
    """`pid` and its descendants (the node's worker processes), from /proc."""
    tree, k = [pid], 0
    while k < len(tree):
        for task in Path(f"/proc/{tree[k]}/task").glob("*"):
            try:
                tree += [int(c) for c in (task / "children").read_text().split()]
            except OSError:  # the task ended meanwhile
                pass
        k += 1
    return tree


def _proc_sum(pid: int, one, tree: bool = True) -> float:
    total = 0.0
    for p in process_tree(pid) if tree else [pid]:
        try:
            total += one(p)
        except (OSError, ValueError):  # ended meanwhile
            pass
    return total


def rss_mb(pid: int) -> float:
    """Resident memory of the node and its worker processes, MB (shared pages counted in each)."""
    def one(p: int) -> float:
        line = next(x for x in Path(f"/proc/{p}/status").read_text().splitlines() if x.startswith("VmRSS:"))
        return int(line.split()[1]) / 1024
    return _proc_sum(pid, one)


def cpu_seconds(pid: int, tree: bool = True) -> float:
    """User + system CPU time of the node and its worker processes (all their threads), s; `tree` False:
    of the node's own process only."""
    def one(p: int) -> float:
        fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return _proc_sum(pid, one, tree)


def percentiles(values) -> dict[str, float]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"n": 0, "p50": math.nan, "p95": math.nan, "max": math.nan}
    return {"n": int(v.size), "p50": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}


def parse_node_args(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition(":=")
        if not sep or not key:
            raise SystemExit(f"soak: --node-args takes KEY:=VALUE items, got {item!r}")
        out[key] = value
    return out


def soak(args) -> None:
    ns = f"/soak_{os.getpid()}"
    params_file = Path(args.params_file)
    node_params = {"diagnostics.period": "1.0", **parse_node_args(args.node_args)}
    options = ReplayOptions(namespace=ns, params_file=params_file, checkpoint=args.checkpoint, node_params=node_params)
    node = NodeProcess(options, Path(args.node_log or f"/tmp/genreg_soak_{os.getpid()}.log"))
    client = None
    try:
        t_load = time.monotonic()
        clouds = load_clouds(args)  # while the node starts
        t_load = time.monotonic() - t_load
        reliability = node_params.get("qos.publisher_reliability") or yaml_param(
            params_file, "qos.publisher_reliability", "reliable")
        # best-effort clouds like a sensor driver; no aligned clouds decoded here (the publisher's CPU)
        client = Client(ns, reliability, input_reliability="best_effort", input_depth=2, aligned=False, status=True,
                        keep_diagnostics=None, name="soak_publisher")
        wait_for_node(client, node, timeout=90.0)
        summary = run_soak(args, node, client, clouds, node_params, t_load)
    finally:
        if client is not None:
            client.close()
        code = node.stop(timeout=30)
    print(f"node exit code on SIGINT: {code} (log: {node.log_path})")
    if args.json:
        summary["node_exit_code"] = code
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=1, default=float) + "\n")
        print(f"summary written to {args.json}")


def run_soak(args, node: NodeProcess, client: Client, clouds: CloudSet, node_params: dict[str, str],
             t_load: float) -> dict:
    pid, params_file = node.proc.pid, Path(args.params_file)
    model = args.checkpoint or yaml_param(params_file, "model.checkpoint", "?")
    refine = node_params.get("refine.method") or yaml_param(params_file, "refine.method", "?")
    print(f"soak: {args.rate:g} Hz pairs for {args.duration:g} s: {clouds.name}, {len(clouds.pairs)} pairs (gap "
          f"{args.gap}) looped, {clouds.points:.0f} points per source cloud ({clouds.megabytes:.1f} MB), serialised "
          f"in {t_load:.1f} s; node pid {pid}: {params_file.name} (model {model}, refine {refine}) "
          f"+ {' '.join(f'{k}:={v}' for k, v in node_params.items())}, sync.slop 0.001 (relay); QoS best effort, "
          f"shipped Fast DDS profile; ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID')}", flush=True)
    print(f"{'t/s':>5s} {'sent':>5s} {'recv':>5s} {'paired':>6s} {'regist':>6s} {'reg/s':>5s} {'supers':>6s} "
          f"{'other':>5s} {'fail':>4s} {'lat ms':>7s} {'RSS MB':>7s}")
    before = client.latest_counters() or {}
    period = 1.0 / args.rate
    sent: list[PairResult] = []
    samples: list[dict] = []  # one per report: time, counters, RSS, CPU
    rss_log: list[tuple[float, float]] = []  # (t, node RSS MB) every second: the growth compares medians

    def report(t: float) -> None:
        d = dict(client.latest_diagnostics() or {})
        other = int(d.get("dropped", 0)) - int(d.get("dropped.superseded", 0))
        reg = int(d.get("registered", 0))
        rate = (reg - samples[-1]["registered"]) / max(t - samples[-1]["t"], 1e-9) if samples else 0.0
        samples.append({"t": round(t, 2), "sent": len(sent), "received_source": int(d.get("received.source", 0)),
                        "paired": int(d.get("paired", 0)), "registered": reg,
                        "superseded": int(d.get("dropped.superseded", 0)), "other_drops": other,
                        "failed": int(d.get("failed", 0)), "latency_ms_median": float(d.get("latency_ms.median", "nan")),
                        "rss_mb": rss_mb(pid), "node_cpu_s": cpu_seconds(pid),
                        "node_process_cpu_s": cpu_seconds(pid, tree=False), "own_cpu_s": time.process_time()})
        s = samples[-1]
        print(f"{t:5.0f} {s['sent']:5d} {s['received_source']:5d} {s['paired']:6d} {reg:6d} {rate:5.1f} "
              f"{s['superseded']:6d} {other:5d} {s['failed']:4d} {d.get('latency_ms.median', '?'):>7s} "
              f"{s['rss_mb']:7.1f}", flush=True)

    t_start = time.monotonic()
    next_tick, next_report, next_rss = t_start, t_start, t_start
    while (now := time.monotonic()) - t_start < args.duration:
        if now >= next_rss:
            rss_log.append((now - t_start, rss_mb(pid)))
            next_rss += 1.0
        if now >= next_report:
            report(now - t_start)
            next_report += 5.0
        if now >= next_tick:
            template = clouds.pairs[len(sent) % len(clouds.pairs)]
            stamp = time.time_ns()
            target, source = restamp(template.target_raw, stamp), restamp(template.source_raw, stamp)
            client.pub_target.publish(target)
            published = time.monotonic()  # the later cloud goes out now
            client.pub_source.publish(source)
            sent.append(dataclasses.replace(template.pair, out_stamp=stamp, published=published, header_problems=[]))
            del target, source
            next_tick += period
            if now - next_tick > 1.0:  # this process fell behind: do not burst
                next_tick = now + period
        time.sleep(max(0.0, min(next_tick, next_report) - time.monotonic()))
    t_end = time.monotonic()
    at_end = {"t": t_end - t_start, "node_cpu_s": cpu_seconds(pid), "node_process_cpu_s": cpu_seconds(pid, tree=False),
              "own_cpu_s": time.process_time(), "rss_mb": rss_mb(pid)}  # the end of the input (the report below comes after settling)
    settle(client, node, sent, timeout=30.0)
    after = client.counters(time.monotonic(), timeout=3.0) or client.latest_counters() or {}
    report(time.monotonic() - t_start)
    return summarize_soak(args, client, clouds, sent, before, after, samples, rss_log, at_end, t_start, t_end,
                          model)


def settle(client: Client, node: NodeProcess, sent: list[PairResult], timeout: float) -> None:
    """Until every sent pair has a transform, or the node's counters stay unchanged for 2.5 s (the last
    registration is done), or the timeout."""
    start = time.monotonic()
    seen, seen_at = None, start
    while (now := time.monotonic()) - start < timeout:
        if not node.alive():
            raise SystemExit(f"soak: the node exited (code {node.proc.returncode}): {node.error_line()}")
        with client.lock:
            if all(p.out_stamp in client.transforms for p in sent):
                return
        counts = client.latest_counters()
        if counts != seen:
            seen, seen_at = counts, now
        elif now - seen_at >= 2.5:
            return
        time.sleep(0.2)


def summarize_soak(args, client: Client, clouds: CloudSet, sent: list[PairResult], before: dict[str, int],
                   after: dict[str, int], samples: list[dict], rss_log: list[tuple[float, float]],
                   at_end: dict[str, float], t_start: float, t_end: float, model: str) -> dict:
    """Match the node's outputs to the sent pairs by stamp, account for every pair, print the summary block."""
    deltas = counter_deltas(after, before)
    with client.lock:
        transforms, status = dict(client.transforms), dict(client.status)
        diag_log = list(client.diags)
    stamps = {p.out_stamp for p in sent}
    for p in sent:
        tf = transforms.get(p.out_stamp)
        if tf is None:
            continue
        p.T_est, p.received = tf.T, tf.received
        if tf.frame_id != p.target_frame_id or tf.child_frame_id != p.source_frame_id:
            p.header_problems.append(f"transform {tf.frame_id!r} <- {tf.child_frame_id!r}")
    assign_reasons(sent, deltas)
    s = summarize(sent, deltas, [])
    reg = [p for p in sent if p.registered]
    n, duration, warmup = len(sent), args.duration, min(args.warmup, args.duration)
    steady = [p for p in reg if t_start + warmup <= p.received <= t_end]
    node_latency = percentiles([float(status[p.out_stamp]["latency_ms"]) for p in reg if p.out_stamp in status])
    e2e = percentiles([1e3 * p.latency for p in reg])
    errors = [p.errors(p.T_est) for p in reg]
    identity = [p.errors(np.eye(4)) for p in reg]

    def success(errs) -> float:
        return float(np.mean([re < SUCCESS_RE_DEG and te < SUCCESS_TE_M for re, te in errs])) if errs else math.nan

    warm = next((x for x in samples if x["t"] >= warmup - 0.5), samples[-1])
    # RSS swings by tens of MB with the clouds in flight: the growth compares the medians of the 1 Hz samples
    # of the first and the last `window` seconds after the warm-up, and a line fit gives the trend.
    steady_rss = [(t, m) for t, m in rss_log if t >= warm["t"]] + [(at_end["t"], at_end["rss_mb"])]
    window = min(10.0, (at_end["t"] - warm["t"]) / 2)
    first_w = med([m for t, m in steady_rss if t <= warm["t"] + window])
    last_w = med([m for t, m in steady_rss if t >= at_end["t"] - window])
    slope = float(np.polyfit(*zip(*steady_rss, strict=True), 1)[0]) if len(steady_rss) >= 3 else math.nan
    rss = {"first": samples[0]["rss_mb"], "warmup_end": warm["rss_mb"], "warmup_end_t": warm["t"],
           "end": at_end["rss_mb"], "after_settling": samples[-1]["rss_mb"],
           "max": max(m for _, m in [*rss_log, (0, at_end["rss_mb"])]),
           "min_after_warmup": min(m for _, m in steady_rss), "max_after_warmup": max(m for _, m in steady_rss),
           "window_s": window, "median_first_window": first_w, "median_last_window": last_w,
           "growth_after_warmup": last_w - first_w, "end_minus_warmup_end": at_end["rss_mb"] - warm["rss_mb"],
           "slope_mb_per_min": 60 * slope, "samples_1hz": rss_log}
    span = max(at_end["t"] - warm["t"], 1e-9)  # from the warm-up end to the last publication
    cpu = {"node": (at_end["node_cpu_s"] - warm["node_cpu_s"]) / span,
           "node_process": (at_end["node_process_cpu_s"] - warm["node_process_cpu_s"]) / span,
           "publisher": (at_end["own_cpu_s"] - warm["own_cpu_s"]) / span}
    cpu["workers"] = cpu["node"] - cpu["node_process"]
    steady_diag = [d for t, d in diag_log if t_start + warmup <= t <= t_end]
    timing_keys = ("decode_ms", "preprocess_ms", "register_ms", "encode_ms", "publish_ms", "points_registered",
                   "points_target", "confidence", "guess_won", "guard_won")
    timings = {k: med([float(d[f"last.{k}"]) for d in steady_diag if f"last.{k}" in d]) for k in timing_keys}
    for k in ("callback_ms.median", "overhead_ms.median"):
        timings[k] = med([float(d[k]) for d in steady_diag if k in d])
    starts = Counter(status[p.out_stamp].get("start", "?") for p in reg if p.out_stamp in status)
    reasons = s["reasons"]
    superseded = sum(v for k, v in reasons.items() if k == "node dropped.superseded")
    lost = s["lost"]  # no output and not counted by the node: both clouds lost in transport (best effort)
    lost_in_transport = min(n - deltas.get("received.source", 0), n - deltas.get("received.target", 0))
    other = n - len(reg) - superseded - lost
    node_paired = after.get("paired", 0) - before.get("paired", 0)
    node_failed = sum(v for k, v in deltas.items() if k.startswith("failed."))
    node_superseded = deltas.get("dropped.superseded", 0)
    node_registered = deltas.get("registered", 0)
    node_reset = deltas.get("dropped.reset", 0)
    node_ok = node_paired == node_registered + node_failed + node_superseded + node_reset
    summary = {
        "clouds": clouds.name, "pairs_in_loop": len(clouds.pairs), "gap": args.gap,
        "points_per_cloud": clouds.points, "mb_per_cloud": clouds.megabytes,
        "params_file": str(args.params_file), "model": model,
        "node_params": {"sync.slop": "0.001", "diagnostics.period": "1.0", **parse_node_args(args.node_args)},
        "ros_domain_id": os.environ.get("ROS_DOMAIN_ID"),
        "rate_hz": args.rate, "duration_s": duration, "warmup_s": warmup,
        "sent": n, "sent_rate_hz": n / duration,
        "node_received": {"source": deltas.get("received.source", 0), "target": deltas.get("received.target", 0)},
        # sent but never received, by the publisher's sequence numbers (the node's `missed.*`)
        "node_missed": {"source": deltas.get("missed.source", 0), "target": deltas.get("missed.target", 0)},
        "node_paired": node_paired, "node_registered": node_registered,
        "registered": len(reg), "registered_per_s": len(reg) / duration,
        "light": deltas.get("light", 0),  # registered with the light settings under the latency budget
        "registered_per_s_after_warmup": len(steady) / max(duration - warmup, 1e-9),
        "superseded": superseded, "other_not_registered": other, "lost": lost,
        "not_registered_by_reason": reasons,
        "node_drop_and_fail_counts": {k: v for k, v in sorted(deltas.items()) if k.startswith(("dropped.", "failed."))},
        "accounted": len(reg) + superseded + other + lost == n and lost <= lost_in_transport,
        "pairs_with_both_clouds_lost_at_most": lost_in_transport,
        "node_accounted": node_ok,
        "outputs_not_matching_a_sent_pair": sum(1 for st in transforms if st not in stamps),
        "header_problems": s["header_problems"],
        "latency_ms": {"node": node_latency, "end_to_end": e2e},
        "rss_mb": rss, "cpu_cores_after_warmup": cpu,
        "accuracy": {"pairs": len(reg), "re_deg_median": s["re"]["median"], "te_m_median": s["te"]["median"],
                     "re_deg_p95": s["re"]["p95"], "te_m_p95": s["te"]["p95"], "success_share": success(errors),
                     "identity_re_deg_median": s["identity_re"]["median"],
                     "identity_te_m_median": s["identity_te"]["median"], "identity_success_share": success(identity),
                     "criterion": f"RE < {SUCCESS_RE_DEG:g} deg and TE < {SUCCESS_TE_M:g} m"},
        "node_timings_median_of_1hz_samples": timings, "winning_start": dict(starts),
        "table": samples,
    }
    summary["acceptance"] = {
        "rate": summary["registered_per_s"] >= goal_rate(args.rate), "p95": node_latency["p95"] <= GOAL_P95_MS,
        "rss_flat": rss["growth_after_warmup"] <= args.rss_tolerance,  # a drop is no leak
    }
    print_summary(summary, args)
    return summary


def print_summary(m: dict, args) -> None:
    def lat(x: dict) -> str:
        return f"{x['p50']:.0f} / {x['p95']:.0f} / {x['max']:.0f} ms (n {x['n']})"

    def ok(flag: bool) -> str:
        return "OK" if flag else "NOT MET"

    a, r, t, acc = m["acceptance"], m["rss_mb"], m["node_timings_median_of_1hz_samples"], m["accuracy"]
    reasons = ", ".join(f"{k} {v}" for k, v in m["not_registered_by_reason"].items()) or "none"
    counts = ", ".join(f"{k} {v}" for k, v in m["node_drop_and_fail_counts"].items()) or "none"
    lines: list[str] = []
    add = lines.append
    add(f"summary: {m['clouds']}, {m['pairs_in_loop']} pairs (gap {m['gap']}) looped; model {m['model']}, "
        f"{Path(m['params_file']).name}")
    add(f"  input        {args.rate:g} Hz for {m['duration_s']:g} s: {m['sent']} pairs sent ({m['sent_rate_hz']:.1f} Hz, "
        f"{m['points_per_cloud']:.0f} points, {m['mb_per_cloud']:.1f} MB per cloud); node received "
        f"{m['node_received']['source']} sources / {m['node_received']['target']} targets (missed "
        f"{m['node_missed']['source']} / {m['node_missed']['target']}), paired {m['node_paired']}")
    add(f"  registered   {m['registered']} pairs = {m['registered_per_s']:.1f} per second "
        f"({m['registered_per_s_after_warmup']:.1f} after the {m['warmup_s']:g} s warm-up); goal >= {goal_rate(args.rate):.3g}; "
        f"light (latency budget) {m['light']}")
    add(f"  not regist.  {m['sent'] - m['registered']}: {reasons}")
    add(f"  accounted    registered {m['registered']} + superseded {m['superseded']} + other {m['other_not_registered']} "
        f"+ lost in transport {m['lost']} = "
        f"{m['registered'] + m['superseded'] + m['other_not_registered'] + m['lost']} of {m['sent']} sent: "
        f"{'yes' if m['accounted'] else 'NO'}; node counts: {counts}")
    add(f"  latency      node p50 / p95 / max {lat(m['latency_ms']['node'])} (goal p95 <= {GOAL_P95_MS:g}); "
        f"end-to-end {lat(m['latency_ms']['end_to_end'])}")
    add(f"  RSS          warm-up end ({r['warmup_end_t']:.0f} s) {r['warmup_end']:.1f} MB, end {r['end']:.1f} MB "
        f"({r['end_minus_warmup_end']:+.1f}); growth {r['growth_after_warmup']:+.1f} MB (median of the last "
        f"{r['window_s']:.0f} s - of the first {r['window_s']:.0f} s after warm-up), fit {r['slope_mb_per_min']:+.1f} "
        f"MB/min; range after warm-up {r['min_after_warmup']:.1f}-{r['max_after_warmup']:.1f} MB")
    add(f"  accuracy     {acc['pairs']} registered pairs: RE median {acc['re_deg_median']:.3f} deg, TE median "
        f"{1e3 * acc['te_m_median']:.1f} mm, success {100 * acc['success_share']:.1f} % ({acc['criterion']}); "
        f"identity on the same pairs: {acc['identity_re_deg_median']:.3f} deg, {1e3 * acc['identity_te_m_median']:.1f} "
        f"mm, {100 * acc['identity_success_share']:.1f} %")
    add(f"  node time    per pair (median of 1 Hz samples after warm-up): decode {t['decode_ms']:.1f}, preprocess "
        f"{t['preprocess_ms']:.1f}, register {t['register_ms']:.1f}, encode {t['encode_ms']:.1f}, publish "
        f"{t['publish_ms']:.1f} ms; callback {t['callback_ms.median']:.2f} ms; {t['points_registered']:.0f} source / "
        f"{t['points_target']:.0f} target points registered; winning start "
        f"{', '.join(f'{k} {v}' for k, v in m['winning_start'].items()) or '-'}")
    cpu, rate = m["cpu_cores_after_warmup"], m["registered_per_s_after_warmup"]
    per_pair = ", ".join(f"{name} {1e3 * cpu[key] / rate:.1f}" for name, key in
                         (("node process", "node_process"), ("workers", "workers"), ("publisher", "publisher"))
                         ) if rate > 0 else "no pair registered"
    add(f"  CPU          node {cpu['node']:.2f} cores (its own process {cpu['node_process']:.2f}, workers "
        f"{cpu['workers']:.2f}), publisher (this process) {cpu['publisher']:.2f} cores (after warm-up); per "
        f"registered pair: {per_pair} ms")
    add(f"  acceptance   rate {ok(a['rate'])}, p95 {ok(a['p95'])}, RSS flat (growth <= {args.rss_tolerance:g} MB) "
        f"{ok(a['rss_flat'])}")
    print("\n".join(lines), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("overhead", "soak"))
    ap.add_argument("--points", type=int, default=300_000, help="overhead, soak --clouds synthetic: points per cloud")
    ap.add_argument("--pairs", type=int, default=30, help="overhead: pairs measured")
    ap.add_argument("--rate", type=float, default=30.0, help="soak: pairs per second")
    ap.add_argument("--duration", type=float, default=60.0, help="soak: seconds")
    ap.add_argument("--warmup", type=float, default=10.0, help="soak: seconds before RSS and rates count as steady")
    ap.add_argument("--clouds", default="redkitchen",
                    help="soak: a shipped sequence (redkitchen), a bag folder (genreg-make-bag), synthetic or campus")
    ap.add_argument("--start", type=int, default=800, help="soak, sequence: first frame (redkitchen validation: 800)")
    ap.add_argument("--count", type=int, default=200, help="soak, sequence: frames (800-999); campus: scans")
    ap.add_argument("--pixel-stride", type=int, default=1, help="soak, sequence: back-project every n-th pixel")
    ap.add_argument("--gap", type=int, default=1, help="soak: target = frame k - gap, source = frame k")
    ap.add_argument("--campus-seed", type=int, default=7, help="soak --clouds campus: the synthetic campus (0, 1: "
                    "training; 7: held out)")
    ap.add_argument("--params-file", default=str(DEFAULT_PARAMS), help="soak: the node's params file")
    ap.add_argument("--checkpoint", default=None,
                    help="model checkpoint: a shipped name or a .pt path (default: the params file's; overhead 7scenes)")
    ap.add_argument("--node-args", nargs="*", default=[], metavar="KEY:=VALUE",
                    help="soak: more node parameters, e.g. refine.method:=none")
    ap.add_argument("--rss-tolerance", type=float, default=30.0, help="soak: RSS growth after warm-up deemed flat, MB")
    ap.add_argument("--node-log", default=None, help="soak: the node's log file (default /tmp/genreg_soak_<pid>.log)")
    ap.add_argument("--json", default=None, metavar="PATH", help="soak: also write the summary as JSON")
    args = ap.parse_args()
    overhead(args) if args.mode == "overhead" else soak(args)


if __name__ == "__main__":
    main()
