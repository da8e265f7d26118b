"""register_node's odometry (map mode, `map.odometry`): where the localised frame was at a stamp in the
odometry frame, and how it moved between two stamps.

Pure Python (no rclpy), thread-safe. The node keeps the poses of nav_msgs/Odometry messages (T_odom_child:
header.frame_id the odometry frame, e.g. odom, child_frame_id the localised frame, e.g. base_link) for
`KEEP_NS`, in stamp order. A pose at a stamp between two kept ones is their constant-twist interpolation (the
screw motion between them, `genreg_core.geometry.extrapolate`); after the newest, the last two's motion goes on
for at most `REACH_NS` (a scan stamped a little after the last odometry message); elsewhere there is none.
Tracking starts a scan from the last accepted pose moved by the odometry's motion since its stamp
(`Tracker.start`, origin `odometry`), and a published pose gives the map -> odometry frame transform at its
stamp (REP-105: T_map_odom = T_map_child T_odom_child^-1).
"""

from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass

import numpy as np

from genreg_core.geometry import extrapolate, invert_transform

KEEP_NS = 30_000_000_000  # odometry kept this long before the newest message (the last accepted pose's stamp)
REACH_NS = 200_000_000  # the newest odometry's motion goes on this far beyond it
GAP_NS = 1_000_000_000  # no pose between two kept ones further apart (the odometry paused)


@dataclass(frozen=True)
class OdometryPose:
    """The localised frame's pose in the odometry frame at a stamp: T_frame_child (`frame`, `child`)."""

    T: np.ndarray
    frame: str
    child: str


class Odometry:
    """The kept odometry of one node: `add` each message's pose, ask `at` a stamp or for the `motion` between
    two."""

    def __init__(self, keep_ns: int = KEEP_NS, reach_ns: int = REACH_NS) -> None:
        self.keep_ns, self.reach_ns = keep_ns, reach_ns
        self._lock = threading.Lock()
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._frames = ("", "")  # (frame, child) of the kept poses

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp: int, T: np.ndarray, frame: str, child: str) -> None:
        """Keep the pose T_frame_child at `stamp` (ns). A message naming other frames than the kept ones, or
        stamped more than `keep_ns` before the newest (the clock went back), starts the odometry afresh; one
        with a kept stamp replaces that pose."""
        with self._lock:
            if (frame, child) != self._frames or (self._stamps and stamp < self._stamps[-1] - self.keep_ns):
                self._stamps, self._poses, self._frames = [], [], (frame, child)
            k = bisect.bisect_left(self._stamps, stamp)
            if k < len(self._stamps) and self._stamps[k] == stamp:
                self._poses[k] = T
            else:
                self._stamps.insert(k, stamp)
                self._poses.insert(k, T)
            old = bisect.bisect_left(self._stamps, self._stamps[-1] - self.keep_ns)
            del self._stamps[:old], self._poses[:old]

    def at(self, stamp: int, child: str | None = None) -> OdometryPose | None:
        """The pose at `stamp` (ns): interpolated between the kept poses around it, or the newest moved on by
        the last two's motion for at most `reach_ns` after it; None before the oldest, beyond the reach, between
        two poses more than `GAP_NS` apart, with fewer than two poses kept (one when `stamp` is its own), or when
        the kept odometry tracks another frame than `child` (if given)."""
        with self._lock:
            stamps, poses, (frame, kept) = self._stamps, self._poses, self._frames
            if child is not None and kept != child:
                return None
            k = bisect.bisect_left(stamps, stamp)
            if k < len(stamps) and stamps[k] == stamp:
                return OdometryPose(poses[k], frame, kept)
            if len(stamps) < 2 or k == 0 or stamp > stamps[-1] + self.reach_ns:
                return None
            k = min(k, len(stamps) - 1)  # after the newest: the last two
            (a, A), (b, B) = (stamps[k - 1], poses[k - 1]), (stamps[k], poses[k])
        if b - a > GAP_NS:
            return None
        # A (A^-1 B)^s, s = (stamp - a) / (b - a): `extrapolate` from B by s - 1 of the motion from A to B
        return OdometryPose(extrapolate(A, B, (stamp - b) / (b - a)), frame, kept)

    def motion(self, start: int, end: int, child: str) -> np.ndarray | None:
        """How the frame `child` moved from stamp `start` to stamp `end` (ns): T_child(start)_child(end), or None
        when the odometry does not cover both stamps or tracks another frame."""
        a, b = self.at(start, child), self.at(end, child)
        return None if a is None or b is None else invert_transform(a.T) @ b.T

    @property
    def child(self) -> str:
        """The frame the kept odometry tracks ("" before the first message)."""
        return self._frames[1]
