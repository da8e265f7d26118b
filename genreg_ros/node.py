"""register_node: GenReg registration of two PointCloud2 streams as a ROS 2 node.

Topics (relative names, remap them):
- in  `source_cloud`, `target_cloud` (sensor_msgs/PointCloud2), paired by header stamp (see sync.py);
- in  `initial_guess` (geometry_msgs/TransformStamped, T_target_source), overrides the parameter;
- out `aligned_cloud` (PointCloud2): the source's finite points moved into the target frame, every other
  field kept; frame_id = target frame, stamp = source stamp;
- out `transform` (TransformStamped): header.frame_id = target frame (parent), child_frame_id = source
  frame, stamp = source stamp: T_target_source (conventions: `genreg_core.geometry`; REP-105 parent/child);
- out `generated_cloud` (PointCloud2, if publish_generated): the network's generated source (A_g) in the
  target frame;
- out `/diagnostics` (diagnostic_msgs/DiagnosticArray): latency, fitness, counts and their reasons.

Threads: subscription callbacks only check headers and pair stamps (O(1) in the cloud size); a worker
thread decodes, registers and publishes. A newer pair replaces an older waiting one, so latency stays one
registration at most and memory is bounded by the sync queues. Bad input is a throttled warning plus a
counted drop; the node carries on.

Parameters: `genreg_ros.config` (the settings) and `genreg_ros.params` (their declaration and checks);
counters and /diagnostics: `genreg_ros.diagnostics`; messages: `genreg_ros.pointcloud2`, `.conversions`.
"""

from __future__ import annotations

import re
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from genreg_core.errors import GenRegError
from genreg_core.preprocess import PreprocessConfig, preprocess
from genreg_ros import params
from genreg_ros.config import NodeConfig
from genreg_ros.conversions import matrix_to_msg, msg_to_matrix, stamp_ns
from genreg_ros.diagnostics import Stats, build_status
from genreg_ros.pointcloud2 import (
    DecodedCloud,
    PointCloud2Error,
    parse_layout,
    read_points,
    transform_cloud,
    xyz_to_msg,
)
from genreg_ros.sync import SOURCE, TARGET, LatestSlot, Pair, PairSync

NODE_NAME = "register_node"
WARN_THROTTLE_S = 2.0  # per drop/failure reason

_DROP_TEXT = {
    "unmatched": "no {other} cloud within sync.slop ({slop} s) of its stamp",
    "queue_full": "sync queue full (sync.queue_size)",
    "no_target": "no target cloud received yet (latest_target mode)",
    "superseded": "a waiting pair was replaced by a newer one (registration slower than the input)",
}


class StartupError(RuntimeError):
    """The node cannot start (bad parameter, unloadable checkpoint, missing tf2_ros); one-line message."""


@dataclass(frozen=True)
class _Cloud:
    """A received cloud with its resolved frame and its arrival time (time.monotonic)."""

    msg: PointCloud2
    frame: str
    received: float


def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name.removesuffix("Error")).lower()


class RegisterNode(Node):
    """The GenReg registration node. Construct inside an rclpy context; call `close()` before destroying."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        try:
            self._config = params.declare(self)
            self._registrar = self._load_registrar(self._config)
            self._tf_broadcaster = self._make_tf_broadcaster() if self._config.publish_tf else None
        except (params.ParamError, StartupError) as exc:
            self.destroy_node()
            raise StartupError(str(exc)) from None
        c = self._config
        self._lock = threading.Lock()  # guards _sync
        self._sync = PairSync(c.sync.slop, c.sync.queue_size, c.sync.mode)
        self._slot = LatestSlot()
        self._stats = Stats()
        self._warned: dict[str, float] = {}
        self._stale: set[str] = set()
        self._guess_topic: np.ndarray | None = None
        self._last_T: np.ndarray | None = None
        self._target_cache: tuple[PointCloud2, DecodedCloud, np.ndarray, PreprocessConfig] | None = None

        sub_qos = QoSProfile(depth=c.qos.depth, reliability=ReliabilityPolicy.RELIABLE)
        if c.qos.reliability == "best_effort":
            sub_qos = QoSProfile(**{**_qos_dict(qos_profile_sensor_data), "depth": c.qos.depth})
        pub_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy[c.qos.publisher_reliability.upper()])
        self._sub_source = self.create_subscription(
            PointCloud2, "source_cloud", lambda m: self._on_cloud(SOURCE, m), sub_qos)
        self._sub_target = self.create_subscription(
            PointCloud2, "target_cloud", lambda m: self._on_cloud(TARGET, m), sub_qos)
        self._sub_guess = self.create_subscription(TransformStamped, "initial_guess", self._on_guess, 1)
        self._pub_aligned = self.create_publisher(PointCloud2, "aligned_cloud", pub_qos)
        self._pub_transform = self.create_publisher(TransformStamped, "transform", pub_qos)
        self._pub_generated = self.create_publisher(PointCloud2, "generated_cloud", pub_qos)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # A steady clock: diagnostics keep coming when sim time (use_sim_time) stalls.
        self._diag_timer = self.create_timer(
            c.diagnostics.period, self._publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.add_on_set_parameters_callback(params.make_validator(lambda: self._config))
        self.add_post_set_parameters_callback(self._on_params_set)
        self._worker = threading.Thread(target=self._work, name="genreg_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ready: model {c.model.checkpoint} (N={self._registrar.num_points}, {c.registration.device}), "
            f"sync {c.sync.mode} slop {c.sync.slop} s, subscription QoS {c.qos.reliability}; "
            f"listening on {self._sub_source.topic_name} and {self._sub_target.topic_name}")

    @property
    def config(self) -> NodeConfig:
        """The settings in force (replaced, never mutated, when parameters change)."""
        return self._config

    @property
    def stats(self) -> Stats:
        """The counters behind /diagnostics (benchmarks read `stats.history`)."""
        return self._stats

    @property
    def registrar(self):
        """The core's `Registrar` the node registers with."""
        return self._registrar

    # ----------------------------------------------------------------- start-up
    def _load_registrar(self, c: NodeConfig):
        from genreg_core.registration import Registrar

        if c.model.num_threads > 0:
            import torch

            torch.set_num_threads(c.model.num_threads)
        try:
            return Registrar.from_checkpoint(c.model.checkpoint, config=c.registration_config(),
                                             num_points=c.model.num_points or None)
        except GenRegError as exc:
            raise StartupError(str(exc)) from None
        except (RuntimeError, AssertionError, OSError) as exc:  # e.g. a cuda device on a CPU-only torch
            raise StartupError(f"cannot load model {c.model.checkpoint!r}: {exc}") from None

    def _make_tf_broadcaster(self):
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError as exc:
            raise StartupError(
                f"publish_tf is true but tf2_ros cannot be imported ({exc}); install tf2_ros (ros-<distro>-tf2-ros) "
                "or set publish_tf to false and use the 'transform' topic") from None
        return TransformBroadcaster(self)

    # ----------------------------------------------------------------- parameters
    def _on_params_set(self, changed: list[Parameter]) -> None:
        config = params.merged(self._config, changed)  # already validated by the on-set callback
        sync_changed = config.sync != self._config.sync
        self._config = config  # replaced, never mutated: readers take one consistent snapshot
        if sync_changed:
            with self._lock:
                self._sync = PairSync(config.sync.slop, config.sync.queue_size, config.sync.mode)

    # ----------------------------------------------------------------- callbacks (short)
    def _on_cloud(self, topic: str, msg: PointCloud2) -> None:
        now = time.monotonic()
        self._stats.arrived(topic, now)
        try:
            c = self._config
            frame = getattr(c, f"{topic}_frame") or msg.header.frame_id
            if not frame:
                self._drop("empty_frame_id", f"{topic} cloud has an empty header.frame_id and {topic}_frame is unset")
                return
            try:
                parse_layout(msg)
            except PointCloud2Error as exc:
                self._drop(exc.reason, f"{topic} cloud: {exc}")
                return
            num = int(msg.width) * int(msg.height)
            if num > c.max_points:
                self._drop("too_many_points", f"{topic} cloud has {num} points, max_points is {c.max_points}")
                return
            stamp = stamp_ns(msg.header)
            with self._lock:
                add = self._sync.add_source if topic == SOURCE else self._sync.add_target
                pair, drops = add(stamp, _Cloud(msg, frame, now))
                slop = self._sync.slop_ns / 1e9
            for d in drops:
                other = TARGET if d.topic == SOURCE else SOURCE
                text = _DROP_TEXT.get(d.reason, d.reason).format(other=other, slop=slop)
                self._drop(d.reason, f"{d.topic} cloud stamped {d.stamp / 1e9:.3f} s dropped: {text}")
            if pair is not None:
                self._stats.pair_formed()
                if self._slot.put(pair) is not None:
                    self._drop("superseded", f"pair dropped: {_DROP_TEXT['superseded']}")
        except Exception as exc:  # noqa: BLE001 (one bad message must never stop the node)
            self._drop("internal_error", f"{topic} cloud: unexpected {type(exc).__name__}: {exc}")
        self._stats.callback.append(time.monotonic() - now)

    def _on_guess(self, msg: TransformStamped) -> None:
        try:
            self._guess_topic = msg_to_matrix(msg)
        except ValueError as exc:
            self._drop("bad_initial_guess", f"initial_guess message ignored: {exc}")

    # ----------------------------------------------------------------- worker
    def _work(self) -> None:
        while not self._slot.closed:
            pair = self._slot.take(timeout=0.5)
            if pair is None:
                continue
            try:
                self._process(pair)
            except Exception as exc:  # noqa: BLE001 (keep the worker alive whatever one pair does)
                self._fail("internal_error", f"unexpected {type(exc).__name__}: {exc}")

    def _process(self, pair: Pair) -> None:
        c = self._config
        src_cloud, tgt_cloud = pair.source, pair.target
        t0 = time.perf_counter()
        try:
            src = read_points(src_cloud.msg, c.max_points)
        except PointCloud2Error as exc:
            self._drop(exc.reason, f"source cloud: {exc}")
            return
        t1 = time.perf_counter()
        try:
            tgt_points, t_tgt = self._decode_target(tgt_cloud.msg, c.max_points, c.preprocess)
        except PointCloud2Error as exc:
            self._drop(exc.reason, f"target cloud: {exc}")
            return
        t2 = time.perf_counter()
        src_points = preprocess(src.points, c.preprocess)
        if self._registrar.config != (cfg := c.registration_config()):
            self._registrar.config = cfg
        t3 = time.perf_counter()
        try:
            result = self._registrar.register(src_points, tgt_points, initial_guess=self._initial_guess(c))
        except GenRegError as exc:
            self._fail(_snake(type(exc).__name__), f"registration failed: {exc}")
            return
        t4 = time.perf_counter()
        if result.fitness < c.min_fitness:
            self._fail("low_fitness", f"fitness {result.fitness:.3f} < min_fitness {c.min_fitness}")
            return
        T_target_source = result.transformation
        header = Header(stamp=src_cloud.msg.header.stamp, frame_id=tgt_cloud.frame)
        aligned = transform_cloud(header, src, T_target_source)
        transform = matrix_to_msg(T_target_source, header, src_cloud.frame)
        t5 = time.perf_counter()
        self._pub_aligned.publish(aligned)
        self._pub_transform.publish(transform)
        if self._tf_broadcaster is not None:
            self._tf_broadcaster.sendTransform(transform)
        if c.publish_generated:
            self._pub_generated.publish(xyz_to_msg(header, result.source_generated))
        t6 = time.perf_counter()
        low_confidence = result.confidence < c.warn_confidence
        if low_confidence:  # published, yet flagged: a user must not mistake it for a good result
            self._warn("low_confidence", f"published a low-confidence result: confidence {result.confidence:.2f} < "
                       f"warn_confidence {c.warn_confidence} (fitness {result.fitness:.2f})")
        self._last_T = T_target_source  # the start of the next pair when use_last_result_as_guess is set
        latency = time.monotonic() - max(src_cloud.received, tgt_cloud.received)
        overhead = (t1 - t0) + t_tgt + (t6 - t4)
        self._stats.ok(latency, overhead, {
            "fitness": result.fitness, "confidence": result.confidence, "inlier_rmse_m": result.inlier_rmse,
            "decode_ms": 1e3 * ((t1 - t0) + t_tgt), "preprocess_ms": 1e3 * ((t3 - t2) + (t2 - t1 - t_tgt)),
            "register_ms": 1e3 * (t4 - t3), "encode_ms": 1e3 * (t5 - t4), "publish_ms": 1e3 * (t6 - t5),
            "points_in": float(src.num_input), "points_registered": float(len(src_points)),
            "initial_guess_won": float(result.start == "initial_guess"),  # the refine guard replaced GenReg
        }, low_confidence)

    def _decode_target(self, msg: PointCloud2, max_points: int, pre: PreprocessConfig) -> tuple[np.ndarray, float]:
        """Preprocessed target points and the decoding time, cached while the same message is reused
        (latest_target)."""
        cache = self._target_cache
        if cache is not None and cache[0] is msg and cache[3] == pre:
            return cache[2], 0.0
        t0 = time.perf_counter()
        decoded = read_points(msg, max_points)
        t_decode = time.perf_counter() - t0
        points = preprocess(decoded.points, pre)
        self._target_cache = (msg, decoded, points, pre)
        return points, t_decode

    def _initial_guess(self, c: NodeConfig) -> np.ndarray | None:
        if self._guess_topic is not None:
            return self._guess_topic
        if c.use_last_result_as_guess and self._last_T is not None:
            return self._last_T
        return c.initial_guess_matrix()

    # ----------------------------------------------------------------- drops, failures, diagnostics
    def _drop(self, reason: str, text: str) -> None:
        self._stats.drop(reason)
        self._warn(reason, f"dropped ({reason}): {text}")

    def _fail(self, reason: str, text: str) -> None:
        self._stats.fail(reason)
        self._warn(reason, f"failed ({reason}): {text}")

    def _warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._warned.get(key, -1e9) >= WARN_THROTTLE_S:
            self._warned[key] = now
            self.get_logger().warning(text)

    def _publish_diagnostics(self) -> None:
        c = self._config
        status, stale = build_status(self._stats.snapshot(), time.monotonic(), self.get_name(),
                                     self.get_fully_qualified_name(), c.diagnostics.stale_timeout,
                                     c.warn_confidence)
        for topic, note in stale.items():
            if topic not in self._stale:
                self.get_logger().warning(f"{note} (topic {self._topic(topic)})")
        self._stale = set(stale)
        self._pub_diag.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now().to_msg()), status=[status]))

    def _topic(self, topic: str) -> str:
        return (self._sub_source if topic == SOURCE else self._sub_target).topic_name

    # ----------------------------------------------------------------- shutdown
    def close(self) -> None:
        """Stop the worker (waits for the pair being registered) and destroy the node."""
        self._slot.close()
        self._worker.join(timeout=10.0)
        self.destroy_node()


def _qos_dict(profile: QoSProfile) -> dict[str, Any]:
    return {
        "history": profile.history, "depth": profile.depth, "reliability": profile.reliability,
        "durability": profile.durability,
    }


def _error(text: str) -> int:
    print(f"{NODE_NAME}: error: {' '.join(text.split())}", file=sys.stderr, flush=True)
    return 1


def main(argv: list[str] | None = None) -> int:
    """Entry point of `ros2 run genreg_ros register_node [--ros-args ...]`; returns the exit code."""
    argv = list(sys.argv if argv is None else argv)
    try:
        for path in params.params_files(argv):
            params.check_params_file(path, params.node_fqn(argv, NODE_NAME))
    except params.ParamError as exc:
        return _error(str(exc))
    try:
        rclpy.init(args=argv)
    except Exception as exc:  # noqa: BLE001 (rcl argument errors: report one line, not a traceback)
        return _error(re.sub(r", at [^,]*:\d+", "", str(exc)))
    node = None
    try:
        node = RegisterNode()
        rclpy.spin(node)
    except StartupError as exc:
        return _error(str(exc))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.close()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
