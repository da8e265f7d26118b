"""register_node: GenReg registration of two PointCloud2 streams as a ROS 2 lifecycle node.

Topics (relative names, remap them):
- in  `source_cloud`, `target_cloud` (sensor_msgs/PointCloud2), paired by header stamp (see sync.py); with
  `target_file` the target is a fixed cloud read from a file and `target_cloud` is not subscribed;
- in  `initial_guess` (geometry_msgs/TransformStamped, T_target_source; frames checked against the pair's)
  and `initialpose` (geometry_msgs/PoseWithCovarianceStamped in the target frame, e.g. RViz's 2D Pose
  Estimate): the source frame's pose in the target frame; both override the parameter and expire after
  `initial_guess_timeout`;
- out `aligned_cloud` (PointCloud2): the source's finite points moved into the target frame, every other
  field kept; frame_id = target frame, stamp = source stamp;
- out `transform` (TransformStamped): header.frame_id = target frame (parent), child_frame_id = source
  frame, stamp = source stamp: T_target_source (conventions: `genreg_core.geometry`; REP-105 parent/child);
- out `pose` (PoseWithCovarianceStamped): the same transform as the source frame's pose in the target frame,
  with the result's 6x6 covariance (x, y, z, rotation about x, y, z; m, rad);
- out `registration_status` (diagnostic_msgs/DiagnosticArray, header = source stamp and target frame): one
  status per result with confidence, fitness, inlier RMSE (m) and which start won;
- out `generated_cloud` (PointCloud2, if publish_generated): the network's generated source (A_g) in the
  target frame;
- out `/diagnostics` (diagnostic_msgs/DiagnosticArray): latency, fitness, counts and their reasons.
Services: the lifecycle services (`<node>/change_state`, `<node>/get_state`, ...), `<node>/reset`
(std_srvs/Trigger: forget tracking, guesses and pairing state) and `<node>/relocalize` (std_srvs/Trigger, map
mode: localise the next scan without a guess).

Map mode (`map.enabled`): the target (`target_file`, or the newest `target_cloud`, e.g. a latched map) is a
prior map and each source scan is localised in it with the core's MapLocalizer (in the node's process,
`workers` 1): without a guess on the first scan, after `~/relocalize` and when tracking is lost, else from
the last accepted pose or a topic guess (`genreg_ros.map_state`: global -> tracking -> lost -> global);
`registration_status` carries the state (`localization`). The map is not preprocessed; the scans are.

Lifecycle: configure loads the model (and the target file) and creates the publishers and the worker;
activate subscribes and enables the publishers; deactivate unsubscribes; cleanup releases everything.
`autostart` (default true) configures and activates at start, so the node runs as a plain node.

Threads: subscription callbacks only check headers and pair stamps (O(1) in the cloud size); a worker
thread decodes and registers, a publisher thread encodes and publishes. With `workers` > 1 there is one
worker thread per worker process (`genreg_ros.workers`: the registration itself runs there) and results
are published in the order their pairs were taken. A newer pair replaces an older waiting one, so latency
stays one registration at most and memory is bounded by the sync queues. Bad input is a throttled warning plus a
counted drop; the node carries on. A stamp more than `sync.slop` older than its topic's newest (bag
loop, simulator reset) resets pairing, tracking and topic guesses, as tf2 clears its buffer on a jump back.
Messages the middleware reports lost (QoS event message_lost) are counted per topic.

Every output of a pair, its `registration_status` included, is published by the publisher thread in the
order the pairs were taken; a rejected result publishes its status alone.

Parameters: `genreg_ros.config` (the settings) and `genreg_ros.params` (their declaration and checks);
what is published: `genreg_ros.policy`; guesses and tracking: `genreg_ros.tracking`; counters and
/diagnostics: `genreg_ros.diagnostics`; messages: `genreg_ros.pointcloud2`, `.conversions`.
"""

from __future__ import annotations

import re
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.executors import ExternalShutdownException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from genreg_core.errors import GenRegError, TooFewPointsError
from genreg_core.memory import retain_freed_memory
from genreg_core.preprocess import PreprocessConfig, preprocess
from genreg_ros import params
from genreg_ros.budget import LatencyBudget
from genreg_ros.config import NodeConfig
from genreg_ros.conversions import matrix_to_msg, matrix_to_pose_msg, msg_to_matrix, stamp_error, stamp_ns
from genreg_ros.diagnostics import Stats, build_status
from genreg_ros.map_state import LOST, TRACKING, Localization, Step, scan_start
from genreg_ros.pointcloud2 import (
    PointCloud2Error,
    from_cdr,
    parse_layout,
    read_points,
    replace_points,
    transform_cloud,
    xyz_to_msg,
)
from genreg_ros.policy import Verdict, judge
from genreg_ros.sync import SOURCE, TARGET, InOrder, LatestSlot, Pair, PairSync
from genreg_ros.tracking import Start, Tracker
from genreg_ros.workers import RemoteRegistrar

NODE_NAME = "register_node"
WARN_THROTTLE_S = 2.0  # per drop/failure reason
MIN_CROPPED_TARGET = 100  # target_crop_radius: fewer points left -> the whole target is used
DOCS = "docs/ros_node.md"
SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
_LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN, "error": DiagnosticStatus.ERROR}

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


@dataclass(frozen=True)
class _FixedTarget:
    """The target_file cloud (metres) in target_frame; `received` is when it was read."""

    points: np.ndarray
    frame: str
    received: float


@dataclass(frozen=True)
class _Prepared:
    """A pair's decoded and preprocessed clouds, with the time spent decoding and preprocessing (s)."""

    source: Any  # the decoded source cloud (DecodedCloud): every field is kept in the aligned cloud
    source_points: np.ndarray  # preprocessed
    target_points: np.ndarray  # preprocessed
    decode_s: float
    preprocess_s: float


@dataclass(frozen=True)
class _Outputs:
    """A published result: what to encode and publish, and the worker's timings for the per-pair statistics."""

    header: Header
    source: Any  # the decoded source cloud (DecodedCloud)
    source_frame: str
    result: Any  # genreg_core RegistrationResult
    latency: float
    overhead: float
    timings: dict[str, float]
    low_confidence: bool
    registered_decoded: bool  # the registered points were the decoded ones (no preprocessing changed them)


@dataclass(frozen=True)
class _Publication:
    """What a registered pair publishes, handed from its worker to the publisher thread (in pair order):
    its registration_status, then its outputs (None: rejected, the status alone)."""

    status: DiagnosticArray
    outputs: _Outputs | None = None


def _figures(prepared: _Prepared, target_points: np.ndarray, result: Any, start_s: float,
             register_s: float) -> dict[str, float]:
    """A registered pair's figures for the statistics (`start_s`: choosing the start and cropping, s)."""
    return {
        "fitness": result.fitness, "confidence": result.confidence, "inlier_rmse_m": result.inlier_rmse,
        "decode_ms": 1e3 * prepared.decode_s, "preprocess_ms": 1e3 * (prepared.preprocess_s + start_s),
        "register_ms": 1e3 * register_s,
        "points_in": float(prepared.source.num_input), "points_registered": float(len(prepared.source_points)),
        "points_target": float(len(target_points)),
        "initial_guess_won": float(result.start == "initial_guess"),  # refinement from the guess won
    }


def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name.removesuffix("Error")).lower()


def failure_reason(exc: GenRegError) -> str:
    """The `failed.<reason>` of a registration error: too_few_points for every TooFewPointsError (its subclass
    NonFinitePointsError included), else the exception's class name in snake case (CheckpointError: checkpoint)."""
    return "too_few_points" if isinstance(exc, TooFewPointsError) else _snake(type(exc).__name__)


_HEADER_BYTES = 65536  # target_file: a PLY or PCD header must end within this many bytes
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_PCD_DATA = ("ascii", "binary", "binary_compressed")


def _cloud_file_problem(suffix: str, head: bytes) -> str:
    """Why `head` (a file's first bytes) is no PLY / PCD point cloud header ("" if it is one). Names what is
    wrong, never quotes the file."""
    if suffix not in (".ply", ".pcd"):
        return f"a .ply or .pcd file is expected, not {suffix or 'no extension'}"
    text = head.decode("latin-1")
    end = "end_header" if suffix == ".ply" else "\nDATA "
    if end not in text:
        return f"no complete {suffix[1:].upper()} header in its first {_HEADER_BYTES} bytes"
    lines = [ln.split() for ln in text.split(end)[0].splitlines()]
    if suffix == ".ply":
        if not lines or lines[0] != ["ply"]:
            return "not a PLY file (its first line is not 'ply')"
        fmt = [ln for ln in lines if ln[:1] == ["format"]]
        if len(fmt) != 1 or len(fmt[0]) != 3 or fmt[0][1] not in _PLY_FORMATS:
            return f"PLY header without a valid format line ({', '.join(_PLY_FORMATS)})"
        vertex = [ln for ln in lines if ln[:2] == ["element", "vertex"]]
        props = {ln[-1] for ln in lines if ln[:1] == ["property"]}
        if not vertex or not {"x", "y", "z"} <= props:
            return "PLY header without a vertex element with x, y, z properties"
        return ""
    fields = next((ln[1:] for ln in lines if ln[:1] == ["FIELDS"]), [])
    data = text.split(end, 1)[1].split(maxsplit=1)[:1]
    if not {"x", "y", "z"} <= set(fields):
        return "PCD header without x, y, z fields"
    if data and data[0] not in _PCD_DATA:
        return f"PCD header with an unknown DATA type (one of {', '.join(_PCD_DATA)} is expected)"
    return ""


def _read_cloud_quietly(path: Path) -> tuple[np.ndarray, bool]:
    """(points, whether the readers printed anything) of a PLY/PCD file read by Open3D with its output and
    RPly's (written straight to stderr) captured and discarded."""
    import ctypes
    import os
    import tempfile

    import open3d as o3d

    sys.stderr.flush()
    sys.stdout.flush()
    saved = os.dup(2), os.dup(1)
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 2)
            os.dup2(sink.fileno(), 1)
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Warning):
                points = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
        finally:
            ctypes.CDLL(None).fflush(None)  # C stdio buffers into the sink, not after it is gone
            os.dup2(saved[0], 2)
            os.dup2(saved[1], 1)
            os.close(saved[0])
            os.close(saved[1])
        printed = sink.seek(0, os.SEEK_END) > 0
    return points, printed


class RegisterNode(LifecycleNode):
    """The GenReg registration node. Construct inside an rclpy context; call `close()` before destroying.

    With `autostart` (the default) the constructor configures and activates it (StartupError if that
    fails); else drive it through the lifecycle services or `trigger_configure()` / `trigger_activate()`."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        try:
            self._config = params.declare(self)
            params.check_overrides(self)
        except params.ParamError as exc:
            self.destroy_node()
            raise StartupError(str(exc)) from None
        c = self._config
        self._lock = threading.Lock()  # guards _sync and _newest (and a reset of both with the tracker)
        self._stats = Stats()
        self._warned: dict[str, float] = {}
        self._stale: set[str] = set()
        self._matched_since: dict[str, float | None] = {SOURCE: None, TARGET: None}
        self._silent_warned: dict[str, float | None] = {}  # topic -> its last arrival when it was warned about
        self._registrars: list[Any] = []  # one per worker: the core's Registrar, or RemoteRegistrars
        self._tf_broadcaster = None
        self._fixed: _FixedTarget | None = None
        self._startup_error = ""
        self._sync = self._new_sync(c)
        self._newest: dict[str, int | None] = {SOURCE: None, TARGET: None}
        self._tracker = Tracker()  # topic guesses and the last result
        self._budget = LatencyBudget()  # full or light registration per pair (budget.latency)
        self._map_state = Localization(c.map.lost_after)  # map mode: global, tracking or lost
        self._localizer: tuple[np.ndarray, Any, str] | None = None  # map mode: (map points, MapLocalizer, frame)
        self._target_cache: tuple[Any, np.ndarray, PreprocessConfig] | None = None
        self._slot = LatestSlot()
        self._take_lock = threading.Lock()  # a pair's ticket is taken with the pair: publication order
        self._workers: list[threading.Thread] = []
        # Encoding and publishing the aligned cloud run on their own thread, so they overlap the next
        # registration; the outbox holds one finished result per worker (workers wait rather than let
        # results pile up) and hands them on in the order the pairs were taken.
        self._outbox = InOrder()
        self._publisher: threading.Thread | None = None
        self._subs: dict[str, Any] = {}
        self._pubs: dict[str, Any] = {}
        self.finalized = Future()  # done after the shutdown transition (main() then exits)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # A steady clock: diagnostics keep coming when sim time (use_sim_time) stalls.
        self._diag_timer = self.create_timer(
            c.diagnostics.period, self._publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._reset_srv = self.create_service(Trigger, "~/reset", self._on_reset)
        self._relocalize_srv = self.create_service(Trigger, "~/relocalize", self._on_relocalize)
        self.add_pre_set_parameters_callback(params.coerce_arrays)
        self.add_on_set_parameters_callback(params.make_validator(lambda: self._config))
        self.add_post_set_parameters_callback(self._on_params_set)
        if c.autostart and (self.trigger_configure() != SUCCESS or self.trigger_activate() != SUCCESS):
            text = self._startup_error or "configure or activate failed"
            self.close()
            raise StartupError(text)

    @property
    def config(self) -> NodeConfig:
        """The settings in force (replaced, never mutated, when parameters change)."""
        return self._config

    @property
    def stats(self) -> Stats:
        """The counters behind /diagnostics."""
        return self._stats

    @property
    def registrar(self):
        """The core's `Registrar` the node registers with, or with `workers` > 1 the first worker's
        `RemoteRegistrar` (None before configure)."""
        return self._registrars[0] if self._registrars else None

    @property
    def state(self) -> str:
        """The lifecycle state's label: unconfigured, inactive, active, finalized (or a transition)."""
        return self._state_machine.current_state[1]

    # ----------------------------------------------------------------- lifecycle
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        c = self._config
        try:
            self._registrars = self._load_registrars(c)
            self._tf_broadcaster = self._make_tf_broadcaster() if c.publish_tf else None
            self._fixed = self._load_target_file(c) if c.target_file else None
        except Exception as exc:  # noqa: BLE001 (rclpy would swallow it: report it as the start-up error)
            self._startup_error = str(exc) if isinstance(exc, StartupError) else \
                f"configure failed: {type(exc).__name__}: {exc}"
            self._close_registrars()
            if not c.autostart:  # with autostart, main() prints it as the one start-up error line
                self.get_logger().error(f"configure failed: {exc}")
            return FAILURE
        pub_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy[c.qos.publisher_reliability.upper()])
        for name, kind in (("aligned_cloud", PointCloud2), ("transform", TransformStamped),
                           ("generated_cloud", PointCloud2), ("pose", PoseWithCovarianceStamped),
                           ("registration_status", DiagnosticArray)):
            self._pubs[name] = self.create_lifecycle_publisher(kind, name, pub_qos)
        with self._lock:
            self._sync = self._new_sync(c)  # latest_target with the file's cloud, if any
        self._reset_state("configure", count=False)
        self._slot = LatestSlot()
        self._workers = [threading.Thread(target=self._work, args=(r,), name=f"genreg_worker_{k}", daemon=True)
                         for k, r in enumerate(self._registrars)]
        self._outbox = InOrder(limit=len(self._workers))
        self._publisher = threading.Thread(target=self._publish_loop, name="genreg_publisher", daemon=True)
        for thread in (*self._workers, self._publisher):
            thread.start()
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        c = self._config
        sub_qos = QoSProfile(depth=c.qos.depth, reliability=ReliabilityPolicy[c.qos.reliability.upper()])
        target_qos = QoSProfile(depth=c.qos.depth, reliability=ReliabilityPolicy[self._target_reliability(c).upper()],
                                durability=DurabilityPolicy[c.qos.target_durability.upper()])
        # clouds arrive serialised (raw=True) and are deserialised by `from_cdr`: 20x faster than rclpy's own
        self._subs[SOURCE] = self._cloud_subscription(SOURCE, sub_qos)
        if self._fixed is None:
            self._subs[TARGET] = self._cloud_subscription(TARGET, target_qos)
        self._subs["guess"] = self.create_subscription(TransformStamped, "initial_guess", self._on_guess, 1)
        self._subs["initialpose"] = self.create_subscription(
            PoseWithCovarianceStamped, "initialpose", self._on_initialpose, 1)
        with self._stats.lock:  # staleness and silent publishers count from activation
            self._stats.start = time.monotonic()
            self._stats.last_arrival = {SOURCE: None, TARGET: None}
        self._matched_since = {SOURCE: None, TARGET: None}
        self._silent_warned.clear()
        target = f"file {c.target_file} ({len(self._fixed.points)} points, frame {self._fixed.frame})" \
            if self._fixed is not None else self._subs[TARGET].topic_name
        mode = "map mode: localising scans in the map " if c.map.enabled else ""
        self.get_logger().info(
            f"ready: {mode}model {c.model.checkpoint} (N={self.registrar.num_points}, {c.registration.device}, "
            f"{f'{c.workers} worker processes' if c.workers > 1 else 'registering in this process'}), "
            f"sync {self._sync.mode} slop {c.sync.slop} s, subscription QoS source {c.qos.reliability}, target "
            f"{self._target_reliability(c)} {c.qos.target_durability}; listening on "
            f"{self._subs[SOURCE].topic_name}, target {target}")
        return super().on_activate(state)

    @staticmethod
    def _target_reliability(c: NodeConfig) -> str:
        """The target subscription's reliability (`QosParams.target_reliability_resolved`)."""
        return c.qos.target_reliability_resolved

    def _cloud_subscription(self, topic: str, qos: QoSProfile):
        """The `<topic>_cloud` subscription (serialised messages), counting the messages the middleware
        reports lost; without that event (an rmw that lacks it) the subscription alone."""
        args = (PointCloud2, f"{topic}_cloud", lambda m: self._on_cloud(topic, m), qos)
        events = SubscriptionEventCallbacks(message_lost=lambda info: self._on_message_lost(topic, info))
        try:
            return self.create_subscription(*args, raw=True, event_callbacks=events)
        except UnsupportedEventTypeError:
            self.get_logger().info(f"the middleware does not report lost messages: {topic} losses are not counted")
            return self.create_subscription(*args, raw=True)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._unsubscribe()
        self._reset_state("deactivate", count=False)
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._unsubscribe()
        self._release()
        self.get_logger().info("shut down (lifecycle)")
        self.finalized.set_result(True)
        return super().on_shutdown(state)

    def _unsubscribe(self) -> None:
        for sub in self._subs.values():
            self.destroy_subscription(sub)
        self._subs.clear()

    def _release(self) -> None:
        """Stop the workers (waits for the pairs being registered), destroy the publishers, drop the model
        (ends the worker processes)."""
        self._slot.close()
        for worker in self._workers:
            worker.join(timeout=10.0)
        self._workers = []
        if self._publisher is not None:  # publishes what the workers handed over, then stops
            self._outbox.close()
            self._publisher.join(timeout=10.0)
            self._publisher = None
        for pub in self._pubs.values():
            self.destroy_lifecycle_publisher(pub)
        self._pubs.clear()
        self._close_registrars()
        self._tf_broadcaster, self._fixed, self._target_cache, self._localizer = None, None, None, None
        self._reset_state("cleanup", count=False)

    # ----------------------------------------------------------------- start-up
    def _load_registrars(self, c: NodeConfig) -> list[Any]:
        """One registrar per worker: the core's Registrar in this process (workers 1), else a worker process
        each (started side by side, after this process has compiled the kernels), each warmed up with a synthetic
        pair (`Registrar.warm_up`) before the node activates. If loading fails, on_configure closes the processes
        started."""
        from genreg_core import kernels
        from genreg_core.registration import Registrar

        num_points = c.model.num_points or None
        self._registrars = [RemoteRegistrar(c.model.checkpoint, c.registration_config(), num_points,
                                            f"genreg_worker_{k}") for k in range(c.workers)] if c.workers > 1 else []
        try:
            # The compiled kernels first (decoding uses them), not at the first pair; the workers started after
            # load them from numba's cache instead of compiling them three times at once (a fresh install: ~50 s).
            kernels.compile_all()
            for r in self._registrars:
                r.start()
            for r in self._registrars:
                r.wait_ready()
            if self._registrars:
                return self._registrars
            local = Registrar.from_checkpoint(c.model.checkpoint, config=c.registration_config(), num_points=num_points)
            local.warm_up()  # as each worker process does before it reports ready
            return [local]
        except GenRegError as exc:
            raise StartupError(str(exc)) from None
        except (RuntimeError, AssertionError, OSError) as exc:  # e.g. a cuda device on a CPU-only torch
            raise StartupError(f"cannot load model {c.model.checkpoint!r}: {exc}") from None

    def _close_registrars(self) -> None:
        for r in self._registrars:
            if isinstance(r, RemoteRegistrar):
                r.close()
        self._registrars = []

    def _make_tf_broadcaster(self):
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError as exc:
            raise StartupError(
                f"publish_tf is true but tf2_ros cannot be imported ({exc}); install tf2_ros (ros-<distro>-tf2-ros) "
                "or set publish_tf to false and use the 'transform' topic") from None
        return TransformBroadcaster(self)

    @staticmethod
    def _load_target_file(c: NodeConfig) -> _FixedTarget:
        """The target_file cloud. Its header is checked here and Open3D reads it with its messages (and
        RPly's, which can quote the file) silenced, so no file content reaches the log; StartupError with a
        one-line message for anything unreadable."""
        path = Path(c.target_file).expanduser()
        if path.is_dir():
            raise StartupError(f"target_file {path} is a directory (a PLY or PCD file is expected)")
        if not path.exists():
            raise StartupError(f"target_file not found: {path}")
        try:
            with path.open("rb") as f:
                head = f.read(_HEADER_BYTES)
        except OSError as exc:
            raise StartupError(f"target_file {path} cannot be read: {exc.strerror or type(exc).__name__}") from None
        problem = _cloud_file_problem(path.suffix.lower(), head)
        if problem:
            raise StartupError(f"target_file {path}: {problem}")
        points, printed = _read_cloud_quietly(path)
        points = points[np.isfinite(points).all(axis=1)]
        if printed or len(points) == 0:
            raise StartupError(f"target_file {path}: {'malformed or truncated' if printed else 'no points read'} "
                               f"({path.suffix[1:].upper()} cloud)")
        return _FixedTarget(points, c.target_frame, time.monotonic())

    # ----------------------------------------------------------------- parameters and state
    def _new_sync(self, c: NodeConfig) -> PairSync:
        """A PairSync for `c`; with a target file it holds that file as the latest target. Map mode pairs each
        scan with the newest map (latest_target)."""
        fixed = getattr(self, "_fixed", None)
        mode = "latest_target" if fixed is not None or c.map.enabled else c.sync.mode
        sync = PairSync(c.sync.slop, c.sync.queue_size, mode)
        if fixed is not None:
            sync.add_target(0, fixed)
        return sync

    def _on_params_set(self, changed: list[Parameter]) -> None:
        config = params.merged(self._config, changed)  # already validated by the on-set callback
        sync_changed = config.sync != self._config.sync
        self._config = config  # replaced, never mutated: readers take one consistent snapshot
        if sync_changed and not config.map.enabled:  # map mode keeps its map (latest_target ignores the rest)
            with self._lock:
                self._sync = self._new_sync(config)

    def _reset_state(self, why: str, count: bool = True) -> None:
        """Forget pairing (queues, newest stamps, the waiting pair), tracking and topic guesses. A fixed or
        latched target in latest_target mode stays."""
        with self._lock:
            self._sync.clear(keep_latest_target=self._sync.mode == "latest_target" and why != "cleanup")
            self._newest = {SOURCE: None, TARGET: None}
            self._tracker.reset()
            self._map_state.relocalize()
        if self._slot.put(None) is not None:
            self._drop("reset", f"a waiting pair was discarded ({why})")
        if count:
            self._stats.event("time_jump" if why.startswith("time jump") else "reset")

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._reset_state("reset service")
        self.get_logger().info("reset: tracking, guesses and pairing state cleared")
        response.success, response.message = True, "tracking, guesses and pairing state cleared"
        return response

    def _on_relocalize(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self._config.map.enabled:
            response.success, response.message = False, "map mode is off (map.enabled false): nothing to relocalise"
            return response
        self._relocalize("relocalize service")
        response.success, response.message = True, "the next scan is localised in the map without a guess"
        return response

    def _relocalize(self, why: str) -> None:
        """Map mode: forget the pose and topic guesses; the next scan is localised globally."""
        with self._lock:
            self._tracker.reset()
            self._map_state.relocalize()
        self._stats.event("relocalize")
        self.get_logger().info(f"relocalize ({why}): the next scan is localised in the map without a guess")

    # ----------------------------------------------------------------- callbacks (short)
    def _on_cloud(self, topic: str, msg: PointCloud2 | bytes) -> None:
        """One cloud, a message or its serialised bytes (the subscriptions' raw=True)."""
        now = time.monotonic()
        self._stats.arrived(topic, now)
        try:
            c = self._config
            if isinstance(msg, bytes):
                try:
                    msg = from_cdr(msg)
                except PointCloud2Error as exc:
                    self._drop(exc.reason, f"{topic} cloud: {exc}")
                    return
            bad_stamp = stamp_error(msg.header)
            if bad_stamp:
                self._drop("bad_stamp", f"{topic} cloud: {bad_stamp}")
                return
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
            newest = self._newest[topic]
            if newest is not None and newest - stamp > round(c.sync.slop * 1e9):  # as tf2: any jump back
                self._reset_state(f"time jump on {topic}")
                self._warn("time_jump", f"time jump: {topic} stamp {stamp / 1e9:.3f} s is {(newest - stamp) / 1e9:.3f} "
                           f"s older than the newest seen ({newest / 1e9:.3f} s), more than sync.slop {c.sync.slop} s "
                           "(bag loop or simulator reset?): pairing, tracking and topic guesses reset")
            with self._lock:
                self._newest[topic] = stamp if self._newest[topic] is None else max(self._newest[topic], stamp)
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
        self._set_guess(msg, msg.header.frame_id, msg.child_frame_id, "initial_guess")

    def _on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        self._set_guess(msg.pose, msg.header.frame_id, None, "initialpose")

    def _on_message_lost(self, topic: str, info: Any) -> None:
        """The middleware's message_lost event (rmw_message_lost_status_t: total_count, total_count_change)."""
        change = int(info.total_count_change)
        self._stats.lost_messages(topic, change)
        self._warn(f"lost_{topic}", f"{change} {topic} cloud(s) lost by the middleware ({int(info.total_count)} in "
                   f"all): large best-effort clouds need config/fastdds_large_clouds.xml in every process; see {DOCS}")

    def _set_guess(self, msg: Any, parent: str, child: str | None, origin: str) -> None:
        try:
            T = msg_to_matrix(msg)
        except ValueError as exc:
            self._drop("bad_initial_guess", f"{origin} message ignored: {exc}")
            return
        self._tracker.set_guess(T, parent, child, origin, time.monotonic())

    # ----------------------------------------------------------------- worker
    def _work(self, registrar: Any) -> None:
        """One worker thread: take the waiting pair (and its place in the publication order), register it
        with `registrar`, hand the result to the publisher."""
        slot, outbox = self._slot, self._outbox
        while not slot.closed:
            with self._take_lock:
                pair = slot.take(timeout=0.5)
                ticket = outbox.ticket() if pair is not None else -1
            if pair is not None:
                outbox.done(ticket, self._survive(lambda p: self._process(p, registrar), pair, ""))

    def _process(self, pair: Pair, registrar: Any) -> _Publication | None:
        """Decode, preprocess, register and judge one pair: what to publish (a rejected result: its status
        alone), or None (dropped or failed: counted)."""
        c = self._config
        prepared = self._prepare(pair, c)
        if prepared is None:
            return None
        t0 = time.perf_counter()
        if c.map.enabled:  # localised in the map: the map state chooses the start
            localizer = self._map_localizer(registrar, c, prepared.target_points, pair.target.frame)
            generation = self._tracker.generation
            if localizer is None:
                return None
            step, start = self._map_start(c, pair)
            target_points = prepared.target_points
            t1 = time.perf_counter()
            result, light = self._localize(localizer, prepared.source_points, start.T), False
        else:
            generation, step = self._tracker.generation, None
            start = self._start(c, pair)
            target_points = self._crop(c, prepared, start.T)
            t1 = time.perf_counter()
            age = time.monotonic() - max(pair.source.received, pair.target.received)
            result, light = self._register(registrar, c, prepared.source_points, target_points, start.T, age)
        if result is None:
            if step is not None:
                self._map_outcome(c, step, hit=False)
            return None
        t2 = time.perf_counter()
        verdict = judge(result, c)
        if step is not None:
            hit = verdict.publish  # a miss: not published (min_confidence, min_fitness)
            verdict = replace(verdict, localization=self._map_outcome(c, step, hit))
        header = Header(stamp=Time(nanoseconds=pair.source_stamp).to_msg(), frame_id=pair.target.frame)
        latency = time.monotonic() - max(pair.source.received, pair.target.received)
        status = self._result_status(result, header, pair.source.frame, start.origin, latency, verdict, light)
        if not verdict.publish:
            self._fail(verdict.reason, verdict.why)
            return _Publication(status)
        if verdict.low_confidence:  # published, yet flagged: a user must not mistake it for a good result
            self._warn("low_confidence", f"published a low-confidence result: confidence {result.confidence:.2f} < "
                       f"warn_confidence {c.warn_confidence} (fitness {result.fitness:.2f})")
        self._tracker.record(result.transformation, pair.source_stamp, generation, time.monotonic())
        timings = _figures(prepared, target_points, result, t1 - t0, t2 - t1)
        # the API moved the registered points; MapLocalizer's are the scan voxelised to the map's resolution
        registered_decoded = not c.map.enabled and prepared.source_points is prepared.source.points
        return _Publication(status, _Outputs(header, prepared.source, pair.source.frame, result, latency,
                                             prepared.decode_s, timings, verdict.low_confidence, registered_decoded))

    # ----------------------------------------------------------------- map mode
    def _map_localizer(self, registrar: Any, c: NodeConfig, map_points: np.ndarray, frame: str) -> Any:
        """The MapLocalizer of this map (built on the first scan after a new map or new registration settings,
        with the node's registrar); a map in another frame than the last one relocalises. None if the map
        cannot be used (counted as failed)."""
        from genreg_core.localization import MapLocalizer

        if registrar.config != (cfg := c.registration_config()):
            registrar.config = cfg
            self._localizer = None  # its screening settings derive from the registrar's
        cached = self._localizer
        if cached is not None and cached[0] is map_points:
            return cached[1]
        cache = None if not c.target_file else Path(c.target_file).expanduser().with_name(
            Path(c.target_file).name + ".genreg-cache")  # a map file's candidate places, kept beside it
        try:
            localizer = MapLocalizer(map_points, registrar=registrar, config=c.map.localization, cache_dir=cache)
        except GenRegError as exc:
            self._fail(failure_reason(exc), f"the map cannot be used: {exc}")
            return None
        if cached is not None and cached[2] != frame:
            self._relocalize(f"the map's frame changed from '{cached[2]}' to '{frame}'")
        self._localizer = (map_points, localizer, frame)
        self.get_logger().info(f"map of {len(map_points)} points in frame '{frame}' ready (resolution "
                               f"{localizer.voxel_size:.3g} m)")
        return localizer

    def _map_start(self, c: NodeConfig, pair: Pair) -> tuple[Step, Start]:
        """The map state's step and the scan's start: a topic guess in any state, else in state tracking the
        last accepted pose, else none (global). The step's mode is how the scan is localised."""
        step = self._map_state.step()
        start = self._tracker.start(c, pair.source.frame, pair.target.frame, time.monotonic(), tracking=True,
                                    parameter=False)
        if start.discarded == "expired":
            self.get_logger().info(start.note)
        elif start.discarded:
            self._drop(start.discarded, start.note)
        return scan_start(step, start)

    def _localize(self, localizer: Any, scan: np.ndarray, guess: np.ndarray | None) -> Any:
        """MapLocalizer's result for the scan (from `guess`, None: globally); None if it failed (counted)."""
        try:
            return localizer.localize(scan, initial_guess=guess)
        except GenRegError as exc:
            self._fail(failure_reason(exc), f"localisation failed: {exc}")
            return None

    def _map_outcome(self, c: NodeConfig, step: Step, hit: bool) -> str:
        """Record a scan's outcome in the map state; the state it is reported in (logged when it changes)."""
        before = self._map_state.state
        state = self._map_state.update(step, hit, c.map.lost_after)
        after = self._map_state.state
        if after == LOST and before != LOST:
            self._stats.event("tracking_lost")
            self.get_logger().warning(f"map mode: tracking lost after {self._map_state.misses} missed scan(s) "
                                      "(map.lost_after); the next scan is localised without a guess")
        elif after == TRACKING and before != TRACKING:
            self.get_logger().info(f"map mode: localised ({step.mode}), tracking")
        return state

    def _prepare(self, pair: Pair, c: NodeConfig) -> _Prepared | None:
        """The pair's clouds decoded and preprocessed; None if one cannot be decoded (counted)."""
        t0 = time.perf_counter()
        try:
            src = read_points(pair.source.msg, c.max_points)
        except PointCloud2Error as exc:
            self._drop(exc.reason, f"source cloud: {exc}")
            return None
        t1 = time.perf_counter()
        try:  # a map (map mode) is not preprocessed: range and crop settings are the sensor's
            target_points, t_target = self._decode_target(pair.target, c.max_points,
                                                          None if c.map.enabled else c.preprocess)
        except PointCloud2Error as exc:
            self._drop(exc.reason, f"target cloud: {exc}")
            return None
        source_points = preprocess(src.points, c.preprocess)
        t2 = time.perf_counter()
        return _Prepared(src, source_points, target_points, (t1 - t0) + t_target, (t2 - t1) - t_target)

    def _start(self, c: NodeConfig, pair: Pair) -> Start:
        """The pair's initial guess (`genreg_ros.tracking`); a topic guess discarded on the way is logged
        (expired) or counted as a drop (frames that are not the pair's)."""
        start = self._tracker.start(c, pair.source.frame, pair.target.frame, time.monotonic())
        if start.discarded == "expired":
            self.get_logger().info(start.note)
        elif start.discarded:
            self._drop(start.discarded, start.note)
        return start

    def _crop(self, c: NodeConfig, prepared: _Prepared, guess: np.ndarray | None) -> np.ndarray:
        """The target points to register against: with target_crop_radius and a fixed or latest target,
        those around the source's predicted position."""
        if c.target_crop_radius > 0 and (self._fixed is not None or self._sync.mode == "latest_target"):
            return self._crop_target(prepared.target_points, prepared.source_points, guess, c.target_crop_radius)
        return prepared.target_points

    def _register(self, registrar: Any, c: NodeConfig, source: np.ndarray, target: np.ndarray,
                  guess: np.ndarray | None, age: float) -> tuple[Any, bool]:
        """The registrar's result under the settings in force, light when the pair (`age` s after its later
        cloud arrived) would miss the latency budget (`genreg_ros.budget`; counted), and whether it was light;
        None if registration failed (counted)."""
        light, cfg = self._budget.plan(age, c.registration_config(), c.budget.latency, c.budget.light_points)
        if registrar.config != cfg:
            registrar.config = cfg
        if light:
            self._stats.event("light")
        t0 = time.perf_counter()
        try:
            result = registrar.register(source, target, initial_guess=guess)
        except GenRegError as exc:
            self._fail(failure_reason(exc), f"registration failed: {exc}")
            return None, light
        self._budget.record(light, time.perf_counter() - t0)
        return result, light

    def _publish_loop(self) -> None:
        while (job := self._outbox.get()) is not None:
            self._survive(self._publish, job, " while publishing")

    def _survive(self, step: Any, item: Any, during: str) -> Any:
        """step(item), counting any exception as a failure (and returning None): the worker and publisher
        threads never die."""
        try:
            return step(item)
        except Exception as exc:  # noqa: BLE001 (keep the thread alive whatever one item does)
            self._fail("internal_error", f"unexpected {type(exc).__name__}{during}: {exc}")
            return None

    def _publish(self, publication: _Publication) -> None:
        """Publish one pair's registration_status, then, unless it was rejected, encode and publish its result
        (aligned cloud, transform, pose, tf, generated cloud) and count it."""
        self._pubs["registration_status"].publish(publication.status)
        job = publication.outputs
        if job is None:
            return
        c, result, header = self._config, job.result, job.header
        t0 = time.perf_counter()
        T_target_source = result.transformation
        if job.registered_decoded and job.source.points.dtype == result.aligned_source.dtype:
            aligned = replace_points(header, job.source, result.aligned_source)  # the API moved these points
        else:
            aligned = transform_cloud(header, job.source, T_target_source)
        transform = matrix_to_msg(T_target_source, header, job.source_frame)
        pose = matrix_to_pose_msg(T_target_source, header, getattr(result, "covariance", None))
        t1 = time.perf_counter()
        self._pubs["aligned_cloud"].publish(aligned)
        self._pubs["transform"].publish(transform)
        self._pubs["pose"].publish(pose)
        if self._tf_broadcaster is not None:
            self._tf_broadcaster.sendTransform(transform)
        if c.publish_generated:
            self._pubs["generated_cloud"].publish(xyz_to_msg(header, result.source_generated))
        t2 = time.perf_counter()
        self._stats.ok(job.latency, job.overhead + (t2 - t0),
                       {**job.timings, "encode_ms": 1e3 * (t1 - t0), "publish_ms": 1e3 * (t2 - t1)},
                       job.low_confidence)

    def _result_status(self, result: Any, header: Header, source_frame: str, guess_origin: str, latency: float,
                       verdict: Verdict, light: bool = False) -> DiagnosticArray:
        """The per-result `registration_status` message (header: the source stamp and the target frame); its
        level and message are the verdict's (`genreg_ros.policy`); in map mode it says the localisation state."""
        values = {
            "confidence": f"{result.confidence:.4f}", "fitness": f"{result.fitness:.4f}",
            "tight_fitness": f"{result.tight_fitness:.4f}", "inlier_ratio": f"{result.inlier_ratio:.4f}",
            "inlier_rmse_m": f"{result.inlier_rmse:.6f}",
            "start": result.start, "initial_guess": guess_origin, "published": str(verdict.publish).lower(),
            "source_frame": source_frame, "target_frame": header.frame_id, "latency_ms": f"{1e3 * latency:.1f}",
            "degenerate": str(verdict.degenerate).lower(), "unconstrained": "; ".join(verdict.unconstrained),
            "budget": "light" if light else "full",
        }
        if verdict.localization:
            values["localization"] = verdict.localization
        status = DiagnosticStatus(level=_LEVELS[verdict.level], name=f"{self.get_name()}: result",
                                  message=verdict.message,
                                  hardware_id=self.get_fully_qualified_name(),
                                  values=[KeyValue(key=k, value=v) for k, v in values.items()])
        return DiagnosticArray(header=header, status=[status])

    def _decode_target(self, target: _Cloud | _FixedTarget, max_points: int,
                       pre: PreprocessConfig | None) -> tuple[np.ndarray, float]:
        """Preprocessed target points (`pre` None: as decoded) and the decoding time, cached while the same
        target is reused (latest_target, target_file, map mode)."""
        key = target.msg if isinstance(target, _Cloud) else target
        cache = self._target_cache
        if cache is not None and cache[0] is key and cache[2] == pre:
            return cache[1], 0.0
        t0 = time.perf_counter()
        points = read_points(target.msg, max_points).points if isinstance(target, _Cloud) else target.points
        t_decode = time.perf_counter() - t0
        points = points if pre is None else preprocess(points, pre)
        self._target_cache = (key, points, pre)
        return points, t_decode

    def _crop_target(self, target: np.ndarray, source: np.ndarray, guess: np.ndarray | None,
                     radius: float) -> np.ndarray:
        """The fixed target's points within `radius` of the source's centre moved by the pose estimate (the
        guess, else the last result); the whole target without an estimate or if too few points are left."""
        T = guess if guess is not None else self._tracker.last_result
        if T is None or len(source) == 0:
            return target
        centre = T[:3, :3] @ source.mean(axis=0) + T[:3, 3]
        kept = target[np.einsum("ij,ij->i", target - centre, target - centre) <= radius * radius]
        if len(kept) < MIN_CROPPED_TARGET:
            self._warn("target_crop", f"target_crop_radius {radius} m keeps {len(kept)} target points around the "
                       "predicted source position; registering against the whole target")
            return target
        return kept

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
        snap, now, state = self._stats.snapshot(), time.monotonic(), self.state
        fixed = self._fixed is not None or (self._sync.mode == "latest_target" and snap.last_arrival[TARGET] is not None)
        silent = self._silent_publishers(snap, now, c.diagnostics.stale_timeout, fixed) if state == "active" else []
        status, stale = build_status(snap, now, self.get_name(), self.get_fully_qualified_name(),
                                     c.diagnostics.stale_timeout, c.warn_confidence, state, fixed, silent,
                                     self._map_state.state if c.map.enabled else "")
        for topic, note in stale.items():
            if topic not in self._stale and topic in self._subs:
                self.get_logger().warning(f"{note} (topic {self._subs[topic].topic_name})")
        self._stale = set(stale)
        self._pub_diag.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now().to_msg()), status=[status]))

    def _silent_publishers(self, snap, now: float, timeout: float, fixed_target: bool = False) -> list[str]:
        """Notes for input topics with a matched publisher whose clouds have not arrived for `timeout` s: none
        since it appeared, or none since the last one (not for a fixed target). Each silence is also warned
        once, with the likely cause."""
        notes = []
        for topic in (SOURCE, TARGET):
            sub = self._subs.get(topic)
            if sub is None:
                continue
            infos = self.get_publishers_info_by_topic(sub.topic_name)
            last = snap.last_arrival[topic]
            if not infos:
                self._matched_since[topic] = None
                continue
            since = self._matched_since[topic] = self._matched_since[topic] or now
            silent = now - max(since, last or since)
            if silent <= timeout or (last is not None and topic == TARGET and fixed_target):
                continue
            kinds = sorted({i.qos_profile.reliability.name.lower() for i in infos})
            what = f"no {topic} cloud" if last is None else f"no new {topic} cloud (publisher stopped delivering)"
            note = f"{len(infos)} publisher(s) on {sub.topic_name} ({', '.join(kinds)}) but {what} for {silent:.1f} s"
            notes.append(note)
            if topic in self._silent_warned and self._silent_warned[topic] == last:
                continue  # warned about this silence already
            self._silent_warned[topic] = last
            cause = ("large best-effort clouds are lost between processes without the shipped Fast DDS profile "
                     "config/fastdds_large_clouds.xml in EVERY process (FASTDDS_DEFAULT_PROFILES_FILE), and clouds "
                     "above its limit are lost even with it")
            if "best_effort" in kinds:
                cause += "; or publish the clouds with a reliable publisher (reliability reliable)"
                if self._topic_reliability(topic) == "reliable":
                    cause = ("a best-effort publisher does not match this node's reliable subscription "
                             f"({'qos.reliability' if topic == SOURCE else 'qos.target_reliability'}); " + cause)
            if last is not None:  # it delivered before
                stopped = "the publisher stopped publishing (driver stalled, bag ended)"
                cause = f"{stopped}, or its clouds grew: {cause}" if "best_effort" in kinds else stopped
            self.get_logger().warning(f"{note}: likely cause: {cause}; see {DOCS} (Large clouds)")
        return notes

    def _topic_reliability(self, topic: str) -> str:
        return self._config.qos.reliability if topic == SOURCE else self._target_reliability(self._config)

    # ----------------------------------------------------------------- shutdown
    def close(self) -> None:
        """Stop the worker (waits for the pair being registered) and destroy the node."""
        self._release()
        self.destroy_node()


def _error(text: str) -> int:
    print(f"{NODE_NAME}: error: {' '.join(text.split())}", file=sys.stderr, flush=True)
    return 1


def main(argv: list[str] | None = None) -> int:
    """Entry point of `ros2 run genreg_ros register_node [--ros-args ...]`; returns the exit code."""
    argv = list(sys.argv if argv is None else argv)
    retain_freed_memory()  # genreg_core.memory: no page faults per registration
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
        rclpy.spin_until_future_complete(node, node.finalized)
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
