"""The replay harness: register_node as a process, an rclpy client that relays bag pairs to it and records
its outputs, and `replay()`, which runs bags through it and scores them (genreg-replay: `.cli`).

Relay: cloud k of a bag is published on `<ns>/source_cloud`, and cloud k - gap (the target) on
`<ns>/target_cloud` with cloud k's stamp, so the node's approximate-time sync pairs them exactly (a node
started here gets sync.slop 1 ms, so a lost message can never be paired with a neighbour's cloud).
Stamps: each bag is shifted to start at the current wall-clock time (the bag's relative timing is kept),
because the node, like any stream consumer, expects stamps to move forward across replays;
keep_stamps publishes the bag's own stamps. The node answers with `transform` (T_target_source, see
`genreg_core.geometry`) and `aligned_cloud`, both stamped with the source's stamp, which is how outputs
are matched to pairs.
Timing: clouds go out at their bag timing divided by `rate` (rate 0: as fast as possible); `lockstep`
waits for each pair's output, or for the node to count it as dropped, before the next one.
Drops: every pair without output gets a reason: a malformed bag message (found by the harness), else a
reason the node counted on /diagnostics (superseded, failed.*, ...), else "lost".

Every rclpy process needs ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, the same ROS_DOMAIN_ID and the Fast
DDS profile config/fastdds_large_clouds.xml (`genreg_ros.environment`); the harness sets them for itself and
the node it starts. `Client` is the one rclpy client of the replay and of scripts/bench_node.py.
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from genreg_ros.bag.reader import BagData, read_bag
from genreg_ros.conversions import msg_to_matrix, split_ns, stamp_ns
from genreg_ros.environment import ros_environment
from genreg_ros.replay.report import format_summary, write_report
from genreg_ros.replay.scoring import (
    ICP_TEXT,
    PairResult,
    assign_reasons,
    make_pairs,
    malformed_clouds,
    run_icp,
    summarize,
)

REPO = Path(__file__).resolve().parents[2]
DEFAULT_PARAMS = REPO / "config" / "genreg.yaml"
NODE_NAME = "register_node"
RELAY_SLOP = 0.001  # s, sync.slop given to a node started here (the relay's pairs have equal stamps)


class ReplayError(RuntimeError):
    """The replay cannot run (node did not start or died, no DDS match, bad bag); one-line message."""


@dataclass
class ReplayOptions:
    """How to replay. Topic names are relative to `namespace`, as the node's are."""

    gap: int = 1  # target = cloud k - gap, source = cloud k
    rate: float = 1.0  # playback speed factor; 0 publishes as fast as possible
    lockstep: bool = False  # wait for each pair's output (or counted drop) before the next
    keep_stamps: bool = False  # publish the bag's stamps instead of shifting them to the current time
    namespace: str = ""
    connect: bool = False  # use a running node instead of starting one
    params_file: Path = DEFAULT_PARAMS
    checkpoint: str | None = None  # model.checkpoint override (None: the params file's)
    node_params: dict[str, str] = field(default_factory=dict)  # more -p overrides, e.g. {"seed": "1"}
    startup_timeout: float = 90.0  # s, node start + DDS discovery
    pair_timeout: float = 30.0  # s, lockstep: longest wait for one pair
    settle_timeout: float = 30.0  # s, after the last publish: longest wait for outputs
    icp: bool = True  # also run Open3D ICP on the same pairs
    report_dir: Path | None = None
    node_log: Path | None = None  # where the started node's output goes (default: report_dir or a temp file)
    verbose: bool = True


@dataclass
class ReplayResult:
    pairs: list[PairResult]
    summary: dict[str, Any]
    text: str
    report: Path | None


# ----------------------------------------------------------------------------- environment and node process
def ros_env(random_domain: bool = True) -> dict[str, str]:
    """`genreg_ros.environment.ros_environment`, set in os.environ for this process and the node it starts.

    ROS_DOMAIN_ID is kept if set; otherwise a random one in 1..100 (random_domain, for a node started here)
    or ROS's default 0 (to reach a running node)."""
    env = ros_environment(None if random_domain or os.environ.get("ROS_DOMAIN_ID") else 0)
    os.environ.update(env)
    return env


def yaml_param(params_file: Path, name: str, default: Any = None) -> Any:
    """A dotted parameter (e.g. 'model.checkpoint') from the first ros__parameters block of a params file."""
    doc = yaml.safe_load(Path(params_file).read_text()) or {}
    for entry in doc.values():
        node = (entry or {}).get("ros__parameters", {})
        for part in name.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if node is not None:
            return node
    return default


class NodeProcess:
    """register_node in a subprocess (`python -m genreg_ros.node --ros-args ...`), output to a log file."""

    def __init__(self, options: ReplayOptions, log_path: Path) -> None:
        args = ["--ros-args", "--params-file", str(options.params_file), "-p", f"sync.slop:={RELAY_SLOP}"]
        if options.namespace.strip("/"):
            args += ["-r", f"__ns:=/{options.namespace.strip('/')}"]
        if options.checkpoint:
            args += ["-p", f"model.checkpoint:={options.checkpoint}"]
        for key, value in options.node_params.items():
            args += ["-p", f"{key}:={value}"]
        self.command = [sys.executable, "-m", "genreg_ros.node", *args]
        self.log_path = log_path
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(log_path, "w")  # noqa: SIM115 (closed in stop())
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(self.command, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                     cwd=REPO, start_new_session=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def error_line(self) -> str:
        """The node's last error line (or the last line of its log)."""
        lines = [ln.strip() for ln in self.log_path.read_text(errors="replace").splitlines() if ln.strip()]
        errors = [ln for ln in lines if "error" in ln.lower()]
        return (errors or lines or [f"exit code {self.proc.returncode}, no output"])[-1]

    def stop(self, timeout: float = 15.0) -> int | None:
        """SIGINT (clean rclpy shutdown), then SIGKILL if it does not exit; returns the exit code."""
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode


# ----------------------------------------------------------------------------- rclpy side
def restamp(raw: bytes, stamp_ns: int) -> bytes:
    """A serialised message whose header stamp (the first field, right after the 4-byte CDR
    encapsulation header) is replaced by stamp_ns."""
    sec, nanosec = split_ns(stamp_ns)
    order = "<" if raw[1] & 1 else ">"
    return raw[:4] + struct.pack(order + "iI", sec, nanosec) + raw[12:]


def _topic(namespace: str, name: str) -> str:
    ns = namespace.strip("/")
    return f"/{ns}/{name}" if ns else f"/{name}"


@dataclass
class Output:
    """One output of the node as the client recorded it: arrival (time.monotonic()), header frame, and the
    transform's child frame and matrix or the aligned cloud's point count and field names."""

    received: float
    frame_id: str
    child_frame_id: str = ""
    T: np.ndarray | None = None
    num_points: int = 0
    fields: tuple[str, ...] = ()


class Client:
    """The harness's rclpy node: publishes pairs, records the node's outputs and /diagnostics.

    Runs its own context and executor thread; outputs are keyed by header stamp (ns): `transforms`,
    `aligned` (unless `aligned` is False: no 300k-point cloud decoded here) and, with `status`, the
    `registration_status` values of each result. `diags`: (arrival, values) of the node's /diagnostics
    status, the last `keep_diagnostics` (None: all). The cloud publishers use `input_reliability` and
    `input_depth` (a soak publishes best effort, like a sensor driver).
    """

    def __init__(self, namespace: str, output_reliability: str = "reliable", *, input_reliability: str = "reliable",
                 input_depth: int = 10, aligned: bool = True, status: bool = False,
                 keep_diagnostics: int | None = 50, name: str = "genreg_replay") -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TransformStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self._rclpy = rclpy
        self.ctx = Context()
        rclpy.init(args=[], context=self.ctx)
        self.node = Node(name, context=self.ctx)
        self.fqn = _topic(namespace, NODE_NAME)
        pub_qos = QoSProfile(depth=input_depth, reliability=ReliabilityPolicy[input_reliability.upper()])
        out_qos = QoSProfile(depth=50, reliability=ReliabilityPolicy[output_reliability.upper()])
        self.pub_source = self.node.create_publisher(PointCloud2, _topic(namespace, "source_cloud"), pub_qos)
        self.pub_target = self.node.create_publisher(PointCloud2, _topic(namespace, "target_cloud"), pub_qos)
        self.lock = threading.Lock()
        self.transforms: dict[int, Output] = {}
        self.aligned: dict[int, Output] = {}
        self.status: dict[int, dict[str, str]] = {}
        self.diags: list[tuple[float, dict[str, str]]] = []
        self.keep_diagnostics = keep_diagnostics
        self.sub_tf = self.node.create_subscription(
            TransformStamped, _topic(namespace, "transform"), self._on_transform, out_qos)
        self.sub_aligned = self.node.create_subscription(
            PointCloud2, _topic(namespace, "aligned_cloud"), self._on_aligned, out_qos) if aligned else None
        if status:
            self.node.create_subscription(
                DiagnosticArray, _topic(namespace, "registration_status"), self._on_status, out_qos)
        self.sub_diag = self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 20)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, name="replay_executor", daemon=True)
        self._thread.start()

    def _on_transform(self, msg: Any) -> None:
        now = time.monotonic()
        out = Output(now, msg.header.frame_id, msg.child_frame_id, msg_to_matrix(msg))
        with self.lock:
            self.transforms[stamp_ns(msg.header)] = out

    def _on_aligned(self, msg: Any) -> None:
        out = Output(time.monotonic(), msg.header.frame_id, num_points=int(msg.width) * int(msg.height),
                      fields=tuple(f.name for f in msg.fields))
        with self.lock:
            self.aligned[stamp_ns(msg.header)] = out

    def _on_status(self, msg: Any) -> None:
        for status in msg.status:
            if status.hardware_id == self.fqn:
                with self.lock:
                    self.status[stamp_ns(msg.header)] = {kv.key: kv.value for kv in status.values}

    def _on_diag(self, msg: Any) -> None:
        now = time.monotonic()
        for status in msg.status:
            if status.hardware_id == self.fqn:
                with self.lock:
                    self.diags.append((now, {kv.key: kv.value for kv in status.values}))
                    if self.keep_diagnostics is not None:
                        del self.diags[:-self.keep_diagnostics]

    def diagnostics(self, newer_than: float, timeout: float) -> dict[str, str] | None:
        """The values of the first /diagnostics status received after `newer_than` (monotonic), waiting up
        to `timeout` s; None if none came."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                fresh = next((d for t, d in self.diags if t > newer_than), None)
            if fresh is not None or time.monotonic() >= deadline:
                return fresh
            time.sleep(0.02)

    def latest_diagnostics(self) -> dict[str, str] | None:
        """The values of the last /diagnostics status received (None: none yet)."""
        with self.lock:
            return self.diags[-1][1] if self.diags else None

    def counters(self, newer_than: float, timeout: float) -> dict[str, int] | None:
        """The node's counters from the first /diagnostics received after `newer_than` (monotonic)."""
        values = self.diagnostics(newer_than, timeout)
        return None if values is None else node_counters(values)

    def latest_counters(self) -> dict[str, int] | None:
        """The node's counters from the last /diagnostics received (None: none yet)."""
        values = self.latest_diagnostics()
        return None if values is None else node_counters(values)

    def matched(self) -> bool:
        return (self.pub_source.get_subscription_count() > 0 and self.pub_target.get_subscription_count() > 0
                and self.sub_tf.get_publisher_count() > 0
                and (self.sub_aligned is None or self.sub_aligned.get_publisher_count() > 0))

    def clear_outputs(self) -> None:
        with self.lock:
            self.transforms.clear()
            self.aligned.clear()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.ctx)
        self._thread.join(timeout=2.0)


def node_counters(values: dict[str, str]) -> dict[str, int]:
    """The counters (registered, paired, light, received.*, missed.*, lost.*, dropped.*, failed.*) of a /diagnostics
    status's values."""
    out = {}
    for key, value in values.items():
        if key in ("registered", "paired", "light") or key.startswith(("dropped.", "failed.", "received.", "missed.",
                                                                        "lost.")):
            try:
                out[key] = int(value)
            except ValueError:
                pass
    return out


def counter_deltas(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    """The counters that grew from `before` to `after`, by how much."""
    return {k: v - before.get(k, 0) for k, v in after.items() if v - before.get(k, 0) > 0}


# ----------------------------------------------------------------------------- the replay of one bag
def _check_alive(node: NodeProcess | None) -> None:
    if node is not None and not node.alive():
        raise ReplayError(f"register_node exited (code {node.proc.returncode}): {node.error_line()}")


def play(bag: BagData, client: Client, options: ReplayOptions, node: NodeProcess | None) -> tuple[
        list[PairResult], dict[str, int]]:
    """Publish the bag's pairs, wait for the outputs; returns the pairs and the node's counter deltas."""
    pairs = make_pairs(bag, options.gap)
    client.clear_outputs()
    before = client.counters(time.monotonic(), timeout=5.0)
    if before is None:
        raise ReplayError(f"no /diagnostics from {client.fqn} within 5 s")
    clouds, t0 = bag.clouds, time.monotonic()
    first = clouds[options.gap].stamp_ns
    offset = 0 if options.keep_stamps else time.time_ns() - first
    for pair in pairs:
        pair.out_stamp = pair.source_stamp + offset
    for pair in pairs:
        if options.rate > 0:
            delay = t0 + (pair.source_stamp - first) / 1e9 / options.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        _check_alive(node)
        client.pub_target.publish(restamp(clouds[pair.k - options.gap].raw, pair.out_stamp))
        source = clouds[pair.k].raw if options.keep_stamps else restamp(clouds[pair.k].raw, pair.out_stamp)
        pair.published = time.monotonic()
        client.pub_source.publish(source)
        if options.lockstep:
            _wait_for(client, [pair], options.pair_timeout, node, stable_for=0.9)
    _wait_for(client, pairs, options.settle_timeout, node, stable_for=1.9)
    after = client.counters(time.monotonic() + 0.05, timeout=5.0) or before
    deltas = counter_deltas(after, before)
    _collect(pairs, client)
    assign_reasons(pairs, deltas)
    return pairs, deltas


def _wait_for(client: Client, pairs: list[PairResult], timeout: float, node: NodeProcess | None,
              stable_for: float) -> None:
    """Until every pair has an output, or the node's counters (received, paired, registered, dropped,
    failed) stay unchanged over diagnostics spanning `stable_for` seconds, or the timeout."""
    start = time.monotonic()
    seen: dict[str, int] | None = None
    seen_at = t_last = start
    while time.monotonic() - start < timeout:
        with client.lock:
            if all(p.out_stamp in client.transforms and p.out_stamp in client.aligned for p in pairs):
                return
        _check_alive(node)
        counts = client.counters(t_last, timeout=0.2)
        if counts is None:
            continue
        t_last = time.monotonic()
        if counts != seen:
            seen, seen_at = counts, t_last
        elif t_last - seen_at >= stable_for:
            time.sleep(0.1)  # outputs of the last registration may still be in flight
            return
    # timeout: pairs without output are reported as such


def _collect(pairs: list[PairResult], client: Client) -> None:
    """Copy the outputs into the pairs and check their stamps (by key), frames and point counts."""
    with client.lock:
        transforms, aligned = dict(client.transforms), dict(client.aligned)
    for p in pairs:
        tf, cloud = transforms.get(p.out_stamp), aligned.get(p.out_stamp)
        if tf is None:
            continue
        p.T_est, p.received = tf.T, tf.received
        if tf.frame_id != p.target_frame_id:
            p.header_problems.append(f"transform parent {tf.frame_id!r} != target frame {p.target_frame_id!r}")
        if tf.child_frame_id != p.source_frame_id:
            p.header_problems.append(f"transform child {tf.child_frame_id!r} != source frame {p.source_frame_id!r}")
        if cloud is None:
            p.header_problems.append("no aligned_cloud with the source's stamp")
            continue
        p.aligned_received = cloud.received
        if cloud.frame_id != p.target_frame_id:
            p.header_problems.append(f"aligned frame {cloud.frame_id!r} != target frame {p.target_frame_id!r}")
        if cloud.num_points != p.source_points:
            p.header_problems.append(f"aligned cloud has {cloud.num_points} points, source {p.source_points}")


# ----------------------------------------------------------------------------- the API
def replay(bags: list[str | Path], options: ReplayOptions) -> ReplayResult:
    """Replay bags (one after the other, pairs never span bags) through register_node and evaluate."""
    log = _printer(options.verbose)
    ros_env(random_domain=not options.connect)
    data = []
    for b in bags:
        bag = read_bag(b)
        if not bag.poses:
            log(f"note: {b} has no pose topic: RE/TE cannot be computed")
        data.append(bag)
    node = None
    if not options.connect:
        node_log = options.node_log or (options.report_dir or REPO / "cache" / "replay") / "register_node.log"
        node = NodeProcess(options, Path(node_log))
        log(f"started register_node (pid {node.proc.pid}, log {node_log})")
    # Best effort matches any publisher; a node started here uses its params file's output QoS.
    out_rel = "best_effort" if options.connect else yaml_param(options.params_file, "qos.publisher_reliability",
                                                               "reliable")
    client = None
    try:
        client = Client(options.namespace, options.node_params.get("qos.publisher_reliability", out_rel))
        deadline = time.monotonic() + options.startup_timeout
        while not (client.matched() and client.counters(0.0, timeout=0.05) is not None):
            _check_alive(node)
            if time.monotonic() > deadline:
                raise ReplayError(f"register_node at {client.fqn} not reachable within {options.startup_timeout:.0f} s "
                                  "(same ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE and namespace?)")
            time.sleep(0.1)
        log(f"connected to {client.fqn}; replaying {len(data)} bag(s), gap {options.gap}, "
            + ("lockstep" if options.lockstep else f"rate {options.rate:g}x" if options.rate else "as fast as possible"))
        pairs, counts, malformed = [], Counter(), []
        for bag in data:
            got, deltas = play(bag, client, options, node)
            pairs += got
            counts.update(deltas)
            malformed += malformed_clouds(bag)
    finally:
        if client is not None:
            client.close()
        if node is not None:
            code = node.stop()
            if code not in (0, None, -signal.SIGINT):
                log(f"note: register_node exited with code {code} (log {node.log_path})")
    if options.icp:
        for bag in data:
            run_icp(bag, [p for p in pairs if p.bag == str(bag.path)])
    summary = summarize(pairs, dict(counts), malformed)
    text = format_summary(summary, _title(data, options))
    report = None
    if options.report_dir is not None:
        starts = {str(b.path): b.pose_at(b.clouds[0].stamp_ns) for b in data if b.pose_at(b.clouds[0].stamp_ns) is not None}
        report = write_report(Path(options.report_dir), summary, pairs, text, options.gap, starts,
                              _settings(data, options))
    return ReplayResult(pairs, summary, text, report)


def _title(data: list[BagData], options: ReplayOptions) -> str:
    names = []
    for b in data:
        f = b.frame_numbers
        names.append(f"{b.info.get('sequence', Path(b.path).name)} {f[0]}-{f[-1]}")
    mode = "lockstep" if options.lockstep else f"rate {options.rate:g}x" if options.rate else "as fast as possible"
    model = "of the running node" if options.connect else (
        options.checkpoint or yaml_param(options.params_file, "model.checkpoint", "?"))
    return f"genreg replay: {', '.join(names)} | gap {options.gap} | {mode} | model {model}"


def _settings(data: list[BagData], options: ReplayOptions) -> dict[str, Any]:
    return {
        "title": _title(data, options), "bags": [str(b.path) for b in data], "gap": options.gap,
        "rate": options.rate, "lockstep": options.lockstep, "node": "connected" if options.connect else "started",
        "params_file": str(options.params_file), "checkpoint": options.checkpoint or "(params file)",
        "node_params": {"sync.slop": RELAY_SLOP, **options.node_params} if not options.connect else {},
        "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID"), "icp": ICP_TEXT,
    }


def _printer(verbose: bool):
    def log(text: str) -> None:
        if verbose:
            print(text, file=sys.stderr, flush=True)
    return log
