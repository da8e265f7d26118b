"""register_node: GenReg registration of two PointCloud2 streams as a ROS 2 lifecycle node.

Topics (relative names, remap them):
- in  `source_cloud`, `target_cloud` (sensor_msgs/PointCloud2), paired by header stamp (see sync.py); with
  `target_file` the target is a fixed cloud read from a file and `target_cloud` is not subscribed;
- in  `initial_guess` (geometry_msgs/TransformStamped, T_target_source; frames checked against the pair's)
  and `initialpose` (geometry_msgs/PoseWithCovarianceStamped in the target frame, e.g. RViz's 2D Pose
  Estimate): the source frame's pose in the target frame; both override the parameter and expire after
  `initial_guess_timeout`;
- in  `odom` (nav_msgs/Odometry, with map.odometry): the localised frame's pose in the odometry frame; tracking
  moves the last pose by it (`genreg_ros.odometry`);
- out `aligned_cloud` (PointCloud2): the source's finite points moved into the target frame, every other
  field kept; frame_id = target frame, stamp = source stamp;
- out `transform` (TransformStamped): header.frame_id = target frame (parent), child_frame_id = source
  frame, stamp = source stamp: T_target_source (conventions: `genreg_core.geometry`; REP-105 parent/child);
- out `pose` (PoseWithCovarianceStamped): the same transform as the source frame's pose in the target frame,
  with the result's 6x6 covariance (x, y, z, rotation about x, y, z; m, rad);
- out `registration_status` (diagnostic_msgs/DiagnosticArray, header = source stamp and target frame): one
  status per pair formed: a result's confidence, fitness, inlier RMSE (m) and which start won, or why the
  pair was not registered (superseded, discarded, failed; `genreg_ros.publication`);
- out `odom_transform` (TransformStamped, with map.odometry): the target (map) frame to the odometry frame of
  each published pose, post-dated by map.transform_tolerance, and the last one again every
  map.transform_publish_period while no pose comes (`genreg_ros.publication.MapToOdom`; REP-105; on /tf
  instead of `transform` with publish_tf);
- out `map_cloud` (PointCloud2, map mode with target_file and map.publish_map): the map as localised in, once
  at activation, reliable and transient local (latched);
- out `generated_cloud` (PointCloud2, if publish_generated): the network's generated source (A_g) in the
  target frame;
- out `/diagnostics` (diagnostic_msgs/DiagnosticArray): latency, fitness, counts and their reasons.
Services: the lifecycle services (`<node>/change_state`, `<node>/get_state`, ...), `<node>/reset`
(std_srvs/Trigger: forget tracking, guesses and pairing state) and `<node>/relocalize` (std_srvs/Trigger, map
mode: localise the next scan without a guess).

The node is a shell: lifecycle, parameters, subscriptions, publishers, services and threads. What becomes of
a pair is its pipeline's business (`genreg_ros.pipelines`), chosen once at configure: pairs of the two
topics, a fixed target (`target_file`), or map mode (`map.enabled`: each scan localised in a prior map,
`target_file` or the newest `target_cloud`, with the core's MapLocalizer).

Lifecycle: configure loads the model (and the target file) and creates the publishers, the pipeline and the
worker threads; activate subscribes and enables the publishers; deactivate unsubscribes; cleanup releases
everything. `autostart` (default true) configures and activates at start, so the node runs as a plain node.

Threads: subscription callbacks only check headers and pair stamps (`genreg_ros.intake`, O(1) in the cloud
size); a worker thread per registrar (`genreg_ros.registrar`: in this process, or with `workers` > 1 a worker
process each) hands pairs to the pipeline, and a publisher thread encodes and publishes. A newer pair
replaces an older waiting one (`genreg_ros.sync.Handover`), so latency stays one registration at most and
memory is bounded by the sync queues. Every pair formed gets one `registration_status`, and every output of
a pair, that status included, is published by the publisher thread in the order the pairs left the waiting
slot. Bad input is a throttled warning plus a counted drop; the node carries on. Messages the middleware
reports lost (QoS event message_lost) are counted per topic, and so are the clouds a publisher sent that never
came (gaps in its sequence numbers: a queue that overflowed while the process took no messages, included).

Parameters: `genreg_ros.config` (the settings) and `genreg_ros.params` (their declaration and checks);
what is published: `genreg_ros.policy`; guesses and tracking: `genreg_ros.tracking`; counters and
/diagnostics: `genreg_ros.diagnostics`; messages: `genreg_ros.pointcloud2`, `.conversions`.
"""

from __future__ import annotations

import re
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Odometry as OdometryMsg
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.executors import ExternalShutdownException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import MessageInfo, Subscription
from rclpy.task import Future
from rclpy.timer import Timer
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from genreg_core.memory import retain_freed_memory
from genreg_ros import params
from genreg_ros.cloud_file import CloudFileError, read_cloud
from genreg_ros.config import NodeConfig
from genreg_ros.conversions import msg_to_matrix, stamp_error, stamp_ns
from genreg_ros.diagnostics import DOCS, InputWatch, Reporter, Stats, Watched, build_status
from genreg_ros.intake import CloudPair, FixedTarget, Intake
from genreg_ros.pipelines import Context, Pipeline, make_pipeline
from genreg_ros.publication import MapToOdom, Publication, Publishers, Statuses
from genreg_ros.registrar import LoadError, Registering, close_registrars, load_registrars
from genreg_ros.sync import SOURCE, TARGET, Handover, PairSync
from genreg_ros.tracking import Tracker

if TYPE_CHECKING:
    from rclpy.event_handler import QoSMessageLostInfo
    from tf2_ros import TransformBroadcaster

NODE_NAME = "register_node"
SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
SUPERSEDED = "a newer pair replaced it while it waited (registration slower than the input)"


class StartupError(RuntimeError):
    """The node cannot start (bad parameter, unloadable checkpoint, missing tf2_ros); one-line message."""


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
        self._stats = Stats()
        self._report = Reporter(self._stats, self.get_logger())
        self._statuses = Statuses(self.get_name(), self.get_fully_qualified_name())
        self._tracker = Tracker()  # topic guesses and the last result
        self._intake = Intake(PairSync(c.sync.slop, c.sync.queue_size, c.sync.mode), self._report, self._reset_state)
        self._watch = InputWatch(self.get_publishers_info_by_topic, self.get_logger())
        self._registrars: list[Registering] = []  # one per worker thread
        self._pipeline: Pipeline | None = None  # chosen at configure
        self._handover = Handover()
        self._workers: list[threading.Thread] = []
        self._publisher: threading.Thread | None = None
        self._outputs: Publishers | None = None
        self._odom_timer: Timer | None = None  # repeats the last map -> odom (map.odometry)
        self._subs: dict[str, Subscription] = {}
        self._startup_error = ""
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
    def registrar(self) -> Registering | None:
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
        context = Context(lambda: self._config, self._tracker, self._report, self._statuses)
        try:
            self._registrars = load_registrars(c.model.checkpoint, c.registration_config(), c.model.num_points or None,
                                               c.workers)
            tf = self._tf_broadcaster() if c.publish_tf else None
            fixed = FixedTarget(read_cloud(c.target_file), c.target_frame, time.monotonic(), c.target_file) \
                if c.target_file else None
            self._pipeline = make_pipeline(c, context, self._registrars, fixed)
        except Exception as exc:  # noqa: BLE001 (rclpy would swallow it: report it as the start-up error)
            one_line = isinstance(exc, (StartupError, LoadError, CloudFileError))
            self._startup_error = str(exc) if one_line else f"configure failed: {type(exc).__name__}: {exc}"
            close_registrars(self._registrars)
            self._registrars = []
            if not c.autostart:  # with autostart, main() prints it as the one start-up error line
                self.get_logger().error(f"configure failed: {exc}")
            return FAILURE
        map_to_odom = MapToOdom(round(1e9 * c.map.transform_tolerance), c.map.transform_publish_period) \
            if c.map.odometry else None
        self._outputs = Publishers(self, c.qos.publisher_reliability, self._stats, tf, map_to_odom,
                                   map_cloud=self._pipeline.map_cloud() is not None and c.map.publish_map)
        if map_to_odom is not None and map_to_odom.period > 0.0:  # steady: repeats go on when sim time stalls
            self._odom_timer = self.create_timer(map_to_odom.period / 4, self._repeat_map_to_odom,
                                                 clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._intake.use(self._pipeline.pairing(c))  # latest_target with the file's cloud, if any
        self._reset_state("configure", count=False)
        self._handover = Handover(len(self._registrars))
        self._workers = [threading.Thread(target=self._work, args=(self._pipeline,), name=f"genreg_worker_{k}",
                                          daemon=True) for k in range(len(self._registrars))]
        self._publisher = threading.Thread(target=self._outputs.run, name="genreg_publisher", daemon=True,
                                           args=(self._handover.outbox, lambda: self._config, self._report))
        for thread in (*self._workers, self._publisher):
            thread.start()
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        c, pipeline = self._config, self._pipeline
        target = c.qos.target_reliability_resolved
        self._subs[SOURCE] = self._cloud_subscription(SOURCE, QoSProfile(
            depth=c.qos.depth, reliability=ReliabilityPolicy[c.qos.reliability.upper()]))
        if pipeline.fixed is None:
            self._subs[TARGET] = self._cloud_subscription(TARGET, QoSProfile(
                depth=c.qos.depth, reliability=ReliabilityPolicy[target.upper()],
                durability=DurabilityPolicy[c.qos.target_durability.upper()]))
        self._subs["guess"] = self.create_subscription(TransformStamped, "initial_guess", self._on_guess, 1)
        self._subs["initialpose"] = self.create_subscription(
            PoseWithCovarianceStamped, "initialpose", self._on_initialpose, 1)
        if c.map.odometry:  # best effort (any publisher matches), deep enough for 100 Hz odometry between scans
            self._subs["odom"] = self.create_subscription(
                OdometryMsg, "odom", self._on_odom, QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT))
        self._stats.subscribed()  # staleness, silent publishers and sequence gaps count from activation
        reliability = {SOURCE: c.qos.reliability, TARGET: target}
        self._watch.watch({t: Watched(self._subs[t].topic_name, reliability[t]) for t in reliability if t in self._subs})
        self.get_logger().info(
            f"ready: model {c.model.checkpoint} (N={self.registrar.num_points}, {c.registration.device}, "
            f"{f'{c.workers} worker processes' if c.workers > 1 else 'registering in this process'}), "
            f"sync {self._intake.mode} slop {c.sync.slop} s, subscription QoS source {c.qos.reliability}, target {target} "
            f"{c.qos.target_durability}; listening on {self._subs[SOURCE].topic_name}, "
            f"{pipeline.describe(self._subs[TARGET].topic_name if TARGET in self._subs else '')}")
        done = super().on_activate(state)  # enables the lifecycle publishers
        if "map_cloud" in self._outputs.pubs:
            points, frame = pipeline.map_cloud()
            t0 = time.perf_counter()
            self._outputs.publish_map(points, frame, self.get_clock().now().to_msg())
            self.get_logger().info(f"map published on {self._outputs.pubs['map_cloud'].topic_name} (latched): "
                                   f"{len(points)} points in frame '{frame}' in {time.perf_counter() - t0:.2f} s")
        return done

    def _cloud_subscription(self, topic: str, qos: QoSProfile) -> Subscription:
        """The `<topic>_cloud` subscription (serialised messages: `from_cdr` deserialises them 20x faster than
        rclpy), counting the messages the middleware reports lost; without that event (an rmw that lacks it)
        the subscription alone."""
        args = (PointCloud2, f"{topic}_cloud", lambda m, info: self._on_cloud(topic, m, info), qos)
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
        self._watch.watch({})

    def _release(self) -> None:
        """Stop the workers (waits for the pairs being registered) and the publisher (after it published what
        they handed over), destroy the publishers, drop the pipeline and the model (ends the worker processes)."""
        self._handover.close()
        for thread in self._workers:
            thread.join(timeout=10.0)
        self._handover.outbox.close()
        if self._publisher is not None:
            self._publisher.join(timeout=10.0)
        if self._odom_timer is not None:
            self.destroy_timer(self._odom_timer)
        if self._outputs is not None:
            self._outputs.destroy()
        close_registrars(self._registrars)
        self._workers, self._publisher, self._outputs, self._registrars, self._pipeline = [], None, None, [], None
        self._odom_timer = None
        self._reset_state("cleanup", count=False)

    def _tf_broadcaster(self) -> TransformBroadcaster:
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError as exc:
            raise StartupError(
                f"publish_tf is true but tf2_ros cannot be imported ({exc}); install tf2_ros (ros-<distro>-tf2-ros) "
                "or set publish_tf to false and use the 'transform' topic") from None
        return TransformBroadcaster(self)

    # ----------------------------------------------------------------- parameters, services, state
    def _on_params_set(self, changed: list[Parameter]) -> None:
        config = params.merged(self._config, changed)  # already validated by the on-set callback
        sync_changed = config.sync != self._config.sync
        self._config = config  # replaced, never mutated: readers take one consistent snapshot
        if sync_changed and self._pipeline is not None:
            self._intake.use(self._pipeline.pairing(config))

    def _reset_state(self, why: str, count: bool = True) -> None:
        """Forget pairing (queues, newest stamps, the waiting pair: answered as dropped.reset), tracking and
        topic guesses; map mode localises the next scan globally. A fixed or latched latest target stays
        (not at cleanup)."""
        self._intake.clear(keep_latest_target=why != "cleanup")
        self._tracker.reset()
        if self._pipeline is not None:
            self._pipeline.reset()
        if self._outputs is not None:
            self._outputs.forget_map_to_odom()
        self._unanswered(self._handover.clear(), "reset", f"a waiting pair was discarded ({why})")
        if count:
            self._stats.event("time_jump" if why.startswith("time jump") else "reset")

    def _unanswered(self, left: tuple[CloudPair, int] | None, reason: str, text: str) -> None:
        """Count a pair that left the waiting slot unregistered (dropped.<reason>) and hand its status (WARN,
        not published) to the publisher in its place."""
        if left is not None:
            pair, ticket = left
            self._report.drop(reason, text)
            status = self._statuses.unanswered(pair, "warn", "dropped", reason, text)
            self._handover.outbox.done(ticket, Publication(status), wait=False)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._reset_state("reset service")
        self.get_logger().info("reset: tracking, guesses and pairing state cleared")
        response.success, response.message = True, "tracking, guesses and pairing state cleared"
        return response

    def _on_relocalize(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        done = self._pipeline is not None and self._pipeline.relocalize("relocalize service")
        response.success = done
        response.message = "the next scan is localised in the map without a guess" if done else \
            "map mode is off (map.enabled false) or not configured: nothing to relocalise"
        return response

    # ----------------------------------------------------------------- callbacks (short)
    def _on_cloud(self, topic: str, msg: PointCloud2 | bytes, info: MessageInfo | None = None) -> None:
        """One cloud, a message or its serialised bytes (the subscriptions' raw=True), with its message info:
        counted (and the clouds its publisher sent before it that never came), checked and paired; a pair
        replaces the waiting one, which is answered as superseded."""
        now = time.monotonic()
        if missed := self._stats.arrived(topic, now, info):
            self._report.warn(f"missed_{topic}", f"{missed} {topic} cloud(s) sent but never received (by the "
                              f"publisher's sequence numbers): the subscription's queue (qos.depth "
                              f"{self._config.qos.depth}) overflowed while the node took no messages, or they were "
                              f"lost in transport; see {DOCS}")
        try:
            pair = self._intake.add(topic, msg, now, self._config)
            if pair is not None:
                self._stats.pair_formed()
                self._unanswered(self._handover.put(pair), "superseded", SUPERSEDED)
        except Exception as exc:  # noqa: BLE001 (one bad message must never stop the node)
            self._report.drop("internal_error", f"{topic} cloud: unexpected {type(exc).__name__}: {exc}")
        self._stats.callback.append(time.monotonic() - now)

    def _on_guess(self, msg: TransformStamped) -> None:
        self._set_guess(msg, msg.header.frame_id, msg.child_frame_id, "initial_guess")

    def _on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        self._set_guess(msg.pose, msg.header.frame_id, None, "initialpose")

    def _on_odom(self, msg: OdometryMsg) -> None:
        """Keep an odometry pose (`genreg_ros.odometry`); one that cannot be used is a counted drop."""
        frame, child, localised = msg.header.frame_id, msg.child_frame_id, self._config.base_frame or \
            self._config.source_frame
        try:
            if stamp_error(msg.header) or not frame or not child:
                raise ValueError(stamp_error(msg.header) or "the odometry frame and child frame must be named")
            T = msg_to_matrix(msg.pose)
        except ValueError as exc:
            self._report.drop("bad_odometry", f"odom message ignored: {exc}")
            return
        if localised and child != localised:
            self._report.drop("odometry_frames", f"odom message ignored: it tracks '{child}', the node localises "
                              f"'{localised}'")
            return
        self._tracker.odometry.add(stamp_ns(msg.header), T, frame, child)

    def _set_guess(self, msg: TransformStamped | PoseWithCovarianceStamped, parent: str, child: str | None,
                   origin: str) -> None:
        try:
            T = msg_to_matrix(msg)
        except ValueError as exc:
            self._report.drop("bad_initial_guess", f"{origin} message ignored: {exc}")
            return
        self._tracker.set_guess(T, parent, child, origin, time.monotonic())

    def _on_message_lost(self, topic: str, info: QoSMessageLostInfo) -> None:
        """The middleware's message_lost event (rmw_message_lost_status_t: total_count, total_count_change)."""
        change = int(info.total_count_change)
        self._stats.lost_messages(topic, change)
        self._report.warn(f"lost_{topic}", f"{change} {topic} cloud(s) lost by the middleware ({int(info.total_count)} "
                          f"in all): large best-effort clouds need config/fastdds_large_clouds.xml in every process; "
                          f"see {DOCS}")

    def _work(self, pipeline: Pipeline) -> None:
        """One worker thread: take the waiting pair (with its place in the publication order), hand it to the
        pipeline, hand its publication to the publisher."""
        handover = self._handover
        while not handover.closed:
            taken = handover.take(timeout=0.5)
            if taken is not None:
                handover.outbox.done(taken[1], pipeline.process(taken[0]))

    def _repeat_map_to_odom(self) -> None:
        if self.state == "active":
            self._outputs.repeat_map_to_odom()

    def _publish_diagnostics(self) -> None:
        c, snap, now, state = self._config, self._stats.snapshot(), time.monotonic(), self.state
        fixed = self._intake.holds_target
        silent = self._watch.silent_publishers(snap, now, c.diagnostics.stale_timeout, fixed) if state == "active" else []
        status, stale = build_status(snap, now, self.get_name(), self.get_fully_qualified_name(),
                                     c.diagnostics.stale_timeout, c.warn_confidence, state, fixed, silent,
                                     self._pipeline.localization if self._pipeline is not None else "")
        self._watch.warn_stale(stale)
        self._pub_diag.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now().to_msg()), status=[status]))

    # ----------------------------------------------------------------- shutdown
    def close(self) -> None:
        """Stop the workers (waits for the pairs being registered) and destroy the node."""
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
    except RuntimeError:  # rcl's "context is not valid": SIGINT shut rclpy down while the executor built its wait set
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.close()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
