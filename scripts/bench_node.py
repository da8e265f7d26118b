#!/usr/bin/env python3
"""register_node benchmarks on 300k-point clouds: node overhead, and a 30 Hz soak.

    python scripts/bench_node.py overhead [--points 300000] [--pairs 30]
    python scripts/bench_node.py soak [--rate 30] [--duration 60] [--points 300000]

overhead: the node runs in this process; pairs are sent one at a time and the node's own per-pair
  timings are read back. Overhead = the two subscription callbacks (checks + pairing) + decoding both
  clouds + transforming and encoding the aligned cloud + publishing, i.e. everything on top of
  preprocessing and registration. Goal: median <= 15 ms.
soak: the node runs in its own process (as with `ros2 run`) with the shipped Fast DDS profile; this
  process publishes source/target pairs at --rate for --duration seconds (best effort, like a sensor)
  and prints the node's counters and resident memory (RSS) every 5 s. The node must keep up or drop by
  policy (superseded pairs), and RSS must stay flat.

The model is the shipped scene model `7scenes` unless --checkpoint names another.
ROS isolation: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a random ROS_DOMAIN_ID unless already set.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(REPO / "config" / "fastdds_large_clouds.xml"))

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from genreg_ros.conversions import split_ns
from genreg_ros.pointcloud2 import array_to_msg


def make_clouds(n: int) -> tuple[PointCloud2, PointCloud2]:
    """A source (x, y, z, rgb float32) and the same scene moved by 3 degrees and 10 cm, in two frames."""
    rng = np.random.default_rng(0)
    dt = np.dtype({"names": ["x", "y", "z", "rgb"], "formats": ["<f4"] * 4})
    pts = rng.uniform([0, 0, 0], [20, 15, 3], size=(n, 3))
    pts[: n // 3, 2] = 0.0  # a floor
    c, s = np.cos(np.radians(3)), np.sin(np.radians(3))
    moved = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [0.1, 0.0, 0.0]
    clouds = []
    for frame, p in (("lidar", pts), ("map", moved)):
        rec = np.zeros(n, dt)
        rec["x"], rec["y"], rec["z"] = p.T
        rec["rgb"] = rng.uniform(size=n)
        clouds.append(array_to_msg(Header(frame_id=frame), rec))
    return clouds[0], clouds[1]


def set_stamp(msg: PointCloud2, t_ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = split_ns(t_ns)


def med(values) -> float:
    return float(np.median(values)) if len(values) else float("nan")


# ----------------------------------------------------------------------------------------- overhead
def overhead(args) -> None:
    from genreg_ros.node import RegisterNode

    ckpt = args.checkpoint
    ns = f"/bench_{os.getpid()}"
    rclpy.init()
    node = RegisterNode(namespace=ns, parameter_overrides=[Parameter("model.checkpoint", value=ckpt)])
    helper = rclpy.create_node("bench_helper", namespace=ns)
    qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE)
    pub_s = helper.create_publisher(PointCloud2, "source_cloud", qos)
    pub_t = helper.create_publisher(PointCloud2, "target_cloud", qos)
    got = []
    helper.create_subscription(PointCloud2, "aligned_cloud", lambda m: got.append(m.width), qos)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(helper)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    src, tgt = make_clouds(args.points)
    time.sleep(0.5)
    print(f"node overhead, {args.points} points per cloud ({len(src.data) / 1e6:.1f} MB), {args.pairs} pairs "
          "(+2 warm-up), median; goal <= 15 ms")
    for i in range(args.pairs + 2):
        n0 = node.stats.registered
        set_stamp(src, (1000 + i) * 10**9)
        set_stamp(tgt, (1000 + i) * 10**9)
        pub_s.publish(src)
        pub_t.publish(tgt)
        deadline = time.monotonic() + 30
        while node.stats.registered == n0 and time.monotonic() < deadline:
            time.sleep(0.002)
    with node.stats.lock:
        history = list(node.stats.history)[2:]
        callbacks = list(node.stats.callback)[4:]
        latency = list(node.stats.latency)[2:]
    assert len(history) == args.pairs and all(w == src.width for w in got), "not every pair was registered"
    cb = 2e3 * med(callbacks)
    parts = {k: med([h[k] for h in history]) for k in ("decode_ms", "encode_ms", "publish_ms")}
    total = [2e3 * med(callbacks) + h["decode_ms"] + h["encode_ms"] + h["publish_ms"] for h in history]
    print(f"  2 callbacks (checks + pairing)   {cb:7.2f} ms")
    print(f"  decode source + target           {parts['decode_ms']:7.2f} ms")
    print(f"  transform + encode aligned cloud {parts['encode_ms']:7.2f} ms")
    print(f"  publish aligned + transform      {parts['publish_ms']:7.2f} ms")
    print(f"  overhead total (median per pair) {med(total):7.2f} ms   [{'OK' if med(total) <= 15 else 'ABOVE GOAL'}]")
    print(f"  for reference: preprocess {med([h['preprocess_ms'] for h in history]):.2f} ms, "
          f"registration {med([h['register_ms'] for h in history]):.1f} ms")
    p50, p95 = (1e3 * float(np.percentile(latency, q)) for q in (50, 95))
    print(f"  node latency (later cloud's arrival -> published) p50 {p50:.1f} ms, p95 {p95:.1f} ms")
    executor.shutdown()
    spinner.join(timeout=5)
    node.close()
    helper.destroy_node()
    rclpy.shutdown()


# ----------------------------------------------------------------------------------------- soak
def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def soak(args) -> None:
    ckpt = args.checkpoint
    ns = f"/soak_{os.getpid()}"
    cmd = [sys.executable, "-m", "genreg_ros.node", "--ros-args", "-r", f"__ns:={ns}",
           "-p", f"model.checkpoint:={ckpt}", "-p", "diagnostics.period:=1.0", *args.node_args]
    node_log = open(Path(tempfile.gettempdir()) / f"genreg_soak_{os.getpid()}.log", "w")  # noqa: SIM115
    proc = subprocess.Popen(cmd, stdout=node_log, stderr=subprocess.STDOUT)
    rclpy.init()
    helper = rclpy.create_node("soak_publisher", namespace=ns)
    qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT)
    pub_s = helper.create_publisher(PointCloud2, "source_cloud", qos)
    pub_t = helper.create_publisher(PointCloud2, "target_cloud", qos)
    diag: dict[str, str] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.hardware_id == f"{ns}/register_node":
                diag.clear()
                diag.update({kv.key: kv.value for kv in s.values})

    helper.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(helper)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    src, tgt = make_clouds(args.points)
    deadline = time.monotonic() + 60
    while not diag and time.monotonic() < deadline:
        time.sleep(0.1)
    if not diag:
        raise SystemExit(f"node did not start; see {node_log.name}")
    print(f"soak: {args.rate:g} Hz pairs of {args.points}-point clouds ({len(src.data) / 1e6:.1f} MB each) for "
          f"{args.duration:g} s; node pid {proc.pid}, QoS best effort, shipped Fast DDS profile")
    print(f"{'t/s':>5s} {'sent':>5s} {'recv':>5s} {'paired':>6s} {'regist':>6s} {'supers':>6s} {'other':>5s} "
          f"{'fail':>4s} {'lat ms':>7s} {'RSS MB':>7s}")
    period = 1.0 / args.rate
    t_start = time.monotonic()
    next_tick, next_report, sent, rss = t_start, t_start, 0, []

    def report(t: float) -> None:
        d = dict(diag)
        other = int(d.get("dropped", 0)) - int(d.get("dropped.superseded", 0))
        rss.append(rss_mb(proc.pid))
        print(f"{t:5.0f} {sent:5d} {d.get('received.source', '?'):>5s} {d.get('paired', '?'):>6s} "
              f"{d.get('registered', '?'):>6s} {d.get('dropped.superseded', '0'):>6s} {other:5d} "
              f"{d.get('failed', '?'):>4s} {d.get('latency_ms.median', '?'):>7s} {rss[-1]:7.1f}", flush=True)

    while (now := time.monotonic()) - t_start < args.duration:
        if now >= next_report:
            report(now - t_start)
            next_report += 5.0
        if now >= next_tick:
            stamp = time.time_ns()
            set_stamp(src, stamp)
            set_stamp(tgt, stamp)
            pub_s.publish(src)
            pub_t.publish(tgt)
            sent += 1
            next_tick += period
            if now - next_tick > 1.0:  # this process fell behind: do not burst
                next_tick = now + period
        time.sleep(max(0.0, min(next_tick, next_report) - time.monotonic()))
    time.sleep(2.0)  # let the last diagnostics arrive
    report(time.monotonic() - t_start)
    d = dict(diag)
    paired, registered = int(d.get("paired", 0)), int(d.get("registered", 0))
    superseded = int(d.get("dropped.superseded", 0))
    print(f"summary: sent {sent} pairs ({sent / args.duration:.1f} Hz), node received {d.get('received.source')} "
          f"sources / {d.get('received.target')} targets, paired {paired}, registered {registered} "
          f"({registered / args.duration:.1f} Hz), superseded {superseded}, other drops "
          f"{int(d.get('dropped', 0)) - superseded}, failed {d.get('failed')}; "
          f"every pair accounted: {registered + superseded + int(d.get('failed', 0)) >= paired - 1}")
    print(f"  latency median {d.get('latency_ms.median')} ms, node overhead median {d.get('overhead_ms.median')} ms")
    print(f"  RSS: first {rss[0]:.1f} MB, after 10 s {rss[min(2, len(rss) - 1)]:.1f} MB, last {rss[-1]:.1f} MB, "
          f"max {max(rss):.1f} MB; growth after warm-up {rss[-1] - rss[min(2, len(rss) - 1)]:+.1f} MB")
    executor.shutdown()
    spinner.join(timeout=5)
    helper.destroy_node()
    rclpy.shutdown()
    proc.send_signal(2)
    print(f"node exit code on SIGINT: {proc.wait(timeout=30)} (log: {node_log.name})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("overhead", "soak"))
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--pairs", type=int, default=30, help="overhead: pairs measured")
    ap.add_argument("--rate", type=float, default=30.0, help="soak: pairs per second")
    ap.add_argument("--duration", type=float, default=60.0, help="soak: seconds")
    ap.add_argument("--checkpoint", default="7scenes", help="model checkpoint: a shipped name or a .pt path")
    ap.add_argument("--node-args", nargs="*", default=[], help="soak: extra --ros-args for the node")
    args = ap.parse_args()
    overhead(args) if args.mode == "overhead" else soak(args)


if __name__ == "__main__":
    main()
