"""What register_node publishes for each pair, and the publisher thread that publishes it.

Every pair formed gets one `registration_status` (diagnostic_msgs/DiagnosticArray; header: the pair's source
stamp and target frame), built by `Statuses`:
- a registered pair (`Statuses.result`): level and message from the verdict (`genreg_ros.policy`), values
  confidence, fitness, ..., `published`, `budget`, in map mode `localization`;
- a pair that is not registered (`Statuses.unanswered`): `published: false`, a `reason` (`dropped.superseded`,
  `dropped.reset`, `dropped.<decode reason>`, `failed.<reason>`) and the message of its warning, level WARN
  for a pair replaced or discarded while it waited, ERROR for one that could not be registered.
A `Publication` is a pair's status and, for a published result, its `Outputs`; `Publishers.run` (the
publisher thread) takes the publications in pair order (`genreg_ros.sync.InOrder`) and publishes each: the
status first, then the aligned cloud, transform, pose, tf and generated cloud, encoded on that thread so that
they overlap the next registration.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from rclpy.lifecycle import LifecycleNode
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from genreg_core.geometry import invert_transform
from genreg_core.result import CHECK_SHARES
from genreg_ros.config import NodeConfig
from genreg_ros.conversions import matrix_to_msg, matrix_to_pose_msg, split_ns, stamp_ns
from genreg_ros.diagnostics import Reporter, Stats
from genreg_ros.intake import CloudPair
from genreg_ros.odometry import OdometryPose
from genreg_ros.pointcloud2 import DecodedCloud, replace_points, transform_cloud, xyz_to_msg
from genreg_ros.policy import Level, Verdict
from genreg_ros.sync import InOrder

if TYPE_CHECKING:
    from tf2_ros import TransformBroadcaster

    from genreg_core.result import RegistrationResult

LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN, "error": DiagnosticStatus.ERROR}
OUTPUTS = (("aligned_cloud", PointCloud2), ("transform", TransformStamped), ("generated_cloud", PointCloud2),
           ("pose", PoseWithCovarianceStamped), ("registration_status", DiagnosticArray),
           ("odom_transform", TransformStamped))


@dataclass(frozen=True)
class Outputs:
    """A published result: what to encode and publish, and the worker's timings for the per-pair statistics."""

    header: Header
    source: DecodedCloud  # every field of the source is kept in the aligned cloud
    source_frame: str
    result: RegistrationResult
    latency: float  # s, from the arrival of the pair's later cloud
    overhead: float  # s, the node's work besides preprocessing and registration so far (decoding)
    timings: dict[str, float]
    low_confidence: bool
    registered_decoded: bool  # the registered points were the decoded ones (no preprocessing changed them)
    base_T_source: np.ndarray | None = None  # the result is base_frame's pose: the decoded cloud's mounting on it
    odom: OdometryPose | None = None  # map.odometry: the localised frame's odometry pose at the source stamp


@dataclass(frozen=True)
class Publication:
    """What one pair publishes: its registration_status, then its outputs (None: not published, the status
    alone)."""

    status: DiagnosticArray
    outputs: Outputs | None = None


def pair_header(pair: CloudPair) -> Header:
    """The header of a pair's outputs and status: the source stamp and the target frame."""
    sec, nanosec = split_ns(pair.source_stamp)
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=pair.target.frame)


class Statuses:
    """The registration_status messages of one node (status name `<node>: result`, hardware_id its full name)."""

    def __init__(self, node_name: str, hardware_id: str) -> None:
        self.name = f"{node_name}: result"
        self.hardware_id = hardware_id

    def result(self, result: RegistrationResult, header: Header, source_frame: str, guess_origin: str,
               latency: float, verdict: Verdict, light: bool = False) -> DiagnosticArray:
        """The status of a registered pair: its level and message are the verdict's (`genreg_ros.policy`); in
        map mode it says the localisation state."""
        values = {
            "confidence": f"{result.confidence:.4f}", "fitness": f"{result.fitness:.4f}",
            "tight_fitness": f"{result.tight_fitness:.4f}", "inlier_ratio": f"{result.inlier_ratio:.4f}",
            "inlier_rmse_m": f"{result.inlier_rmse:.6f}",
            "start": result.start, "initial_guess": guess_origin, "published": str(verdict.publish).lower(),
            "source_frame": source_frame, "target_frame": header.frame_id, "latency_ms": f"{1e3 * latency:.1f}",
            "degenerate": str(verdict.degenerate).lower(), "unconstrained": "; ".join(verdict.unconstrained),
            "budget": "light" if light else "full",
        }
        values |= {name: f"{result.verification[name]:.4f}" for name in CHECK_SHARES if name in result.verification}
        if not verdict.publish:
            values["reason"] = f"failed.{verdict.reason}"
        if verdict.localization:
            values["localization"] = verdict.localization
            values["jumped"] = str(verdict.jumped).lower()
        return self._array(header, verdict.level, verdict.message, values)

    def unanswered(self, pair: CloudPair, level: Level, counter: str, reason: str, text: str) -> DiagnosticArray:
        """The status of a pair that was not registered, counted as `counter` (dropped or failed) `.reason`:
        value `reason` that counter's name, message "<counter> (<reason>): <text>", as the log's warning."""
        header = pair_header(pair)
        values = {"published": "false", "reason": f"{counter}.{reason}", "source_frame": pair.source.frame,
                  "target_frame": header.frame_id}
        return self._array(header, level, f"{counter} ({reason}): {text}", values)

    def _array(self, header: Header, level: Level, message: str, values: dict[str, str]) -> DiagnosticArray:
        status = DiagnosticStatus(level=LEVELS[level], name=self.name, message=message, hardware_id=self.hardware_id,
                                  values=[KeyValue(key=k, value=v) for k, v in values.items()])
        return DiagnosticArray(header=header, status=[status])


class MapToOdom:
    """The map -> odometry frame transform as published (map.odometry; `odom_transform` and /tf): one per
    published pose, stamped `tolerance_ns` after the scan's stamp (the time until which it holds, as AMCL's
    transform_tolerance), and, once none was sent for `period` s (0: never), the last one again, stamped on by
    the time since it was sent (steady clock: the scans' own clock, whatever the node's), so that tf lookups go on
    between scans and over missed ones. Stamps only grow (tf warns of a repeated stamp) until `forget` (a reset,
    a time jump back), which also stops the repeats until the next pose. Pure; the caller serialises its calls."""

    def __init__(self, tolerance_ns: int, period: float) -> None:
        self.tolerance_ns, self.period = tolerance_ns, period
        self._last: TransformStamped | None = None
        self._stamp_ns = -1  # of the last one sent
        self._sent_at = 0.0  # when it was sent (monotonic s)

    def fresh(self, msg: TransformStamped, now: float) -> TransformStamped:
        """A published pose's transform (stamped at its scan), stamped as sent at monotonic `now`."""
        return self._send(msg, stamp_ns(msg.header) + self.tolerance_ns, now)

    def again(self, now: float) -> TransformStamped | None:
        """The last transform again if none was sent for `period` s by monotonic `now`, else None."""
        if self._last is None or self.period <= 0.0 or now - self._sent_at < self.period:
            return None
        return self._send(self._last, self._stamp_ns + round(1e9 * (now - self._sent_at)), now)

    def forget(self) -> None:
        self._last, self._stamp_ns = None, -1

    def _send(self, msg: TransformStamped, stamp: int, now: float) -> TransformStamped:
        sec, nanosec = split_ns(max(stamp, self._stamp_ns + 1))
        out = TransformStamped(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=msg.header.frame_id),
                               child_frame_id=msg.child_frame_id, transform=msg.transform)
        self._last, self._stamp_ns, self._sent_at = out, stamp_ns(out.header), now
        return out


class Publishers:
    """The node's per-pair outputs (lifecycle publishers, QoS depth 5 with `reliability`) and tf."""

    def __init__(self, node: LifecycleNode, reliability: str, stats: Stats,
                 tf: TransformBroadcaster | None = None, map_to_odom: MapToOdom | None = None,
                 map_cloud: bool = False) -> None:
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy[reliability.upper()])
        self.pubs = {name: node.create_lifecycle_publisher(kind, name, qos) for name, kind in OUTPUTS}
        if map_cloud:  # latched, as maps are
            self.pubs["map_cloud"] = node.create_lifecycle_publisher(PointCloud2, "map_cloud", QoSProfile(
                depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._node = node
        self._stats = stats
        self._tf = tf
        self._map_to_odom = map_to_odom or MapToOdom(0, 0.0)
        self._odom_lock = threading.Lock()  # the publisher thread's fresh map -> odom, the node's timer's repeats

    def run(self, outbox: InOrder, config: Callable[[], NodeConfig], report: Reporter) -> None:
        """The publisher thread: publish each publication of `outbox`, in order, until it closes. An exception
        is counted (failed.internal_error) and the thread carries on."""
        while (publication := outbox.get()) is not None:
            try:
                self.publish(publication, config().publish_generated)
            except Exception as exc:  # noqa: BLE001 (keep the thread alive whatever one item does)
                report.fail("internal_error", f"unexpected {type(exc).__name__} while publishing: {exc}")

    def publish(self, publication: Publication, generated: bool = False) -> None:
        """Publish one pair's registration_status, then, unless it was not published, encode and publish its
        result (aligned cloud, transform, pose, tf, with `generated` the generated cloud) and count it."""
        self.pubs["registration_status"].publish(publication.status)
        job = publication.outputs
        if job is None:
            return
        result, header = job.result, job.header
        t0 = time.perf_counter()
        T_target_source = result.transformation  # the source frame's (base_frame's, if set) pose
        if job.registered_decoded and job.source.points.dtype == result.aligned_source.dtype:
            aligned = replace_points(header, job.source, result.aligned_source)  # the API moved these points
        else:  # the decoded cloud, in its sensor's frame (mounted on base_frame by base_T_source, if set)
            sensor = T_target_source if job.base_T_source is None else T_target_source @ job.base_T_source
            aligned = transform_cloud(header, job.source, sensor)
        transform = matrix_to_msg(T_target_source, header, job.source_frame)
        pose = matrix_to_pose_msg(T_target_source, header, result.covariance)
        # REP-105: the target (map) frame's transform to the odometry frame, T_map_odom = T_map_child T_odom_child^-1
        odom = None if job.odom is None else \
            matrix_to_msg(T_target_source @ invert_transform(job.odom.T), header, job.odom.frame)
        t1 = time.perf_counter()
        self.pubs["aligned_cloud"].publish(aligned)
        self.pubs["transform"].publish(transform)
        self.pubs["pose"].publish(pose)
        if odom is not None:  # with odometry, map -> odom on /tf (odom -> base is the odometry's)
            with self._odom_lock:
                self._send_odom(self._map_to_odom.fresh(odom, time.monotonic()))
        elif self._tf is not None:
            self._tf.sendTransform(transform)
        if generated:
            self.pubs["generated_cloud"].publish(xyz_to_msg(header, result.source_generated))
        t2 = time.perf_counter()
        self._stats.ok(job.latency, job.overhead + (t2 - t0),
                       {**job.timings, "encode_ms": 1e3 * (t1 - t0), "publish_ms": 1e3 * (t2 - t1)},
                       job.low_confidence)

    def publish_map(self, points: np.ndarray, frame: str, stamp: Time) -> None:
        """The map on map_cloud (created with `map_cloud`), once per activation."""
        self.pubs["map_cloud"].publish(xyz_to_msg(Header(stamp=stamp, frame_id=frame), points))

    def repeat_map_to_odom(self) -> None:
        """The last map -> odom transform again, if none was published for the period (`MapToOdom.again`)."""
        with self._odom_lock:
            if (odom := self._map_to_odom.again(time.monotonic())) is not None:
                self._send_odom(odom)

    def forget_map_to_odom(self) -> None:
        """No more repeats until the next published pose (a reset forgot the pose)."""
        with self._odom_lock:
            self._map_to_odom.forget()

    def _send_odom(self, odom: TransformStamped) -> None:
        self.pubs["odom_transform"].publish(odom)
        if self._tf is not None:
            self._tf.sendTransform(odom)

    def destroy(self) -> None:
        for pub in self.pubs.values():
            self._node.destroy_lifecycle_publisher(pub)
        self.pubs.clear()
