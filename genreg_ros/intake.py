"""What register_node's cloud subscriptions do with each message, in O(1) of the cloud's size: check its
header and layout, notice a jump back in time, and pair it by stamp (`genreg_ros.sync.PairSync`).

A cloud that cannot be used is counted as a drop with its reason (`Reporter.drop`): undecodable_message,
bad_stamp, empty_frame_id, the layout's reasons (`genreg_ros.pointcloud2.parse_layout`), too_many_points;
messages the pairing gives up are counted too (unmatched, queue_full, no_target). A stamp more than
`sync.slop` older than its topic's newest (a bag loop, a simulator reset) calls `on_jump` before the cloud
is paired: the node resets pairing, tracking and topic guesses, as tf2 clears its buffer on a jump back.

The items paired are `Cloud`s, and in latest_target pairing a `FixedTarget` (a file's cloud) may stand for
the target: both give their points with `points(max_points)`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sensor_msgs.msg import PointCloud2

from genreg_ros.config import NodeConfig
from genreg_ros.conversions import stamp_error, stamp_ns
from genreg_ros.diagnostics import Reporter
from genreg_ros.pointcloud2 import PointCloud2Error, from_cdr, parse_layout, read_points
from genreg_ros.sync import SOURCE, TARGET, Pair, PairSync

DROP_TEXT = {
    "unmatched": "no {other} cloud within sync.slop ({slop} s) of its stamp",
    "queue_full": "sync queue full (sync.queue_size)",
    "no_target": "no target cloud received yet (latest_target mode)",
}


@dataclass(frozen=True)
class Cloud:
    """A received cloud (rclpy's message, or rosbags' from `from_cdr`) with its resolved frame and its arrival
    time (time.monotonic)."""

    msg: PointCloud2
    frame: str
    received: float

    def points(self, max_points: int) -> np.ndarray:
        """Its finite points, (K, 3), as decoded; PointCloud2Error if it cannot be decoded."""
        return read_points(self.msg, max_points).points


@dataclass(frozen=True)
class FixedTarget:
    """A target cloud read from a file (`target_file`, metres, finite points) in `frame`; `received`: when it
    was read (time.monotonic)."""

    xyz: np.ndarray
    frame: str
    received: float
    path: str = ""

    def points(self, max_points: int) -> np.ndarray:
        """Its points (read at configure; `max_points` limits received clouds only)."""
        return self.xyz


Target = Cloud | FixedTarget
CloudPair = Pair[Cloud, Target]


class Intake:
    """Checks and pairs the clouds of the two subscriptions. Thread-safe."""

    def __init__(self, sync: PairSync, report: Reporter, on_jump: Callable[[str], None]) -> None:
        self._lock = threading.Lock()  # guards the pairing and the newest stamps
        self._sync = sync
        self._newest: dict[str, int | None] = {SOURCE: None, TARGET: None}
        self._report = report
        self._on_jump = on_jump

    @property
    def holds_target(self) -> bool:
        """Whether every source is paired with one held target (latest_target pairing, a target received or a
        file's): that target is not expected to update."""
        return self._sync.latest_target is not None

    @property
    def mode(self) -> str:
        """The pairing policy in force (`genreg_ros.sync.MODES`)."""
        return self._sync.mode

    def use(self, sync: PairSync) -> None:
        """Pair with `sync` from now on (new settings); a latest target held stays when both pair with it."""
        with self._lock:
            sync.carry_latest_target(self._sync)
            self._sync = sync

    def clear(self, keep_latest_target: bool) -> None:
        """Forget the queued clouds and the newest stamps (not counted as drops); a latest target held stays
        if `keep_latest_target`."""
        with self._lock:
            self._sync.clear(keep_latest_target=keep_latest_target)
            self._newest = {SOURCE: None, TARGET: None}

    def add(self, topic: str, msg: PointCloud2 | bytes, now: float, c: NodeConfig) -> CloudPair | None:
        """One cloud of `topic` (source or target), a message or its serialised bytes, arrived at `now`: the pair
        it completes, if any. A cloud that cannot be used is counted and warned about, and gives None."""
        if isinstance(msg, bytes):
            try:
                msg = from_cdr(msg)
            except PointCloud2Error as exc:
                return self._drop(exc.reason, f"{topic} cloud: {exc}")
        bad_stamp = stamp_error(msg.header)
        if bad_stamp:
            return self._drop("bad_stamp", f"{topic} cloud: {bad_stamp}")
        # the frame a source's pose is of: base_frame (the cloud is moved into it), else the sensor's
        frame = ((c.base_frame or c.source_frame) if topic == SOURCE else c.target_frame) or msg.header.frame_id
        if not frame:
            return self._drop("empty_frame_id", f"{topic} cloud has an empty header.frame_id and {topic}_frame is unset")
        try:
            parse_layout(msg)
        except PointCloud2Error as exc:
            return self._drop(exc.reason, f"{topic} cloud: {exc}")
        num = int(msg.width) * int(msg.height)
        if num > c.max_points:
            return self._drop("too_many_points", f"{topic} cloud has {num} points, max_points is {c.max_points}")
        stamp = stamp_ns(msg.header)
        newest = self._newest[topic]
        if newest is not None and newest - stamp > round(c.sync.slop * 1e9):  # as tf2: any jump back
            self._on_jump(f"time jump on {topic}")
            self._report.warn("time_jump", f"time jump: {topic} stamp {stamp / 1e9:.3f} s is {(newest - stamp) / 1e9:.3f}"
                              f" s older than the newest seen ({newest / 1e9:.3f} s), more than sync.slop "
                              f"{c.sync.slop} s (bag loop or simulator reset?): pairing, tracking and topic guesses reset")
        with self._lock:
            self._newest[topic] = stamp if self._newest[topic] is None else max(self._newest[topic], stamp)
            add = self._sync.add_source if topic == SOURCE else self._sync.add_target
            pair, drops = add(stamp, Cloud(msg, frame, now))
            slop = self._sync.slop_ns / 1e9
        for d in drops:
            other = TARGET if d.topic == SOURCE else SOURCE
            text = DROP_TEXT.get(d.reason, d.reason).format(other=other, slop=slop)
            self._report.drop(d.reason, f"{d.topic} cloud stamped {d.stamp / 1e9:.3f} s dropped: {text}")
        return pair

    def _drop(self, reason: str, text: str) -> None:
        self._report.drop(reason, text)
