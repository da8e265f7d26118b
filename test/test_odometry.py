"""register_node's odometry (`genreg_ros.odometry`), tracking with it (`genreg_ros.tracking`) and the
map -> odom transform it publishes (`genreg_ros.publication.MapToOdom`): no node. The truth is a constant-twist motion, T_odom_base(t) = expm(t xi) (scipy), whose screw interpolation
is exact, and a second motion that turns and speeds up, where a constant velocity is not."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from scipy.linalg import expm
from std_msgs.msg import Header

from genreg_core.geometry import invert_transform
from genreg_ros.config import NodeConfig
from genreg_ros.conversions import stamp_ns
from genreg_ros.odometry import GAP_NS, Odometry
from genreg_ros.publication import MapToOdom
from genreg_ros.tracking import TRACKED, Tracker, motion_continues

MS = 1_000_000  # ns
TWIST = np.array([2.0, 0.3, 0.0, 0.0, 0.0, 0.8])  # vx, vy, vz (m/s), wx, wy, wz (rad/s): driving on a curve
TRACKING = NodeConfig(use_last_result_as_guess=True)


def screw(t: float, twist: np.ndarray = TWIST) -> np.ndarray:
    """T_odom_base at t seconds of a constant twist (body frame): the matrix exponential of its se(3) element."""
    v, w = twist[:3], twist[3:]
    xi = np.zeros((4, 4))
    xi[:3, :3] = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    xi[:3, 3] = v
    return expm(t * xi)


def odometry(stamps_ms: list[int], pose=screw, frame: str = "odom", child: str = "base_link") -> Odometry:
    o = Odometry()
    for s in stamps_ms:
        o.add(s * MS, pose(s / 1000.0), frame, child)
    return o


def test_a_pose_between_two_messages_is_their_screw_interpolation():
    o = odometry(list(range(0, 1001, 20)))  # 50 Hz for a second
    rng = np.random.default_rng(0)
    for t in rng.uniform(0.0, 1.0, 25):
        got = o.at(int(t * 1e9))
        assert got is not None and (got.frame, got.child) == ("odom", "base_link")
        np.testing.assert_allclose(got.T, screw(int(t * 1e9) / 1e9), atol=1e-9)
    np.testing.assert_allclose(o.at(500 * MS).T, screw(0.5), atol=1e-12)  # a message's own stamp: its pose


def test_after_the_newest_message_the_motion_goes_on_for_a_while_then_stops():
    o = odometry([0, 20, 40])
    np.testing.assert_allclose(o.at(150 * MS).T, screw(0.15), atol=1e-9)  # 110 ms after the newest
    assert o.at(40 * MS + o.reach_ns + 1) is None
    assert o.at(-1) is None  # before the oldest
    assert odometry([0]).at(10 * MS) is None and odometry([0]).at(0) is not None  # one message: its stamp only
    gap = odometry([0, GAP_NS // MS + 20])  # the odometry paused for over a second: nothing in between
    assert gap.at(GAP_NS // 2) is None


def test_the_motion_between_two_stamps_is_the_childs_own():
    o = odometry(list(range(0, 501, 10)))
    moved = o.motion(100 * MS, 300 * MS, "base_link")
    np.testing.assert_allclose(moved, invert_transform(screw(0.1)) @ screw(0.3), atol=1e-9)
    np.testing.assert_allclose(moved, screw(0.2), atol=1e-9)  # a constant twist: the same from anywhere
    assert o.motion(100 * MS, 300 * MS, "velodyne") is None  # another frame's odometry tells nothing of this one
    assert o.motion(100 * MS, 900 * MS, "base_link") is None  # not covered


def test_messages_out_of_order_a_clock_jump_and_other_frames():
    o = Odometry()
    for s in (40, 0, 20, 60):  # out of order: kept in stamp order
        o.add(s * MS, screw(s / 1000.0), "odom", "base_link")
    assert len(o) == 4
    np.testing.assert_allclose(o.at(30 * MS).T, screw(0.03), atol=1e-9)
    o.add(20 * MS, screw(0.5), "odom", "base_link")  # the same stamp again: replaced
    np.testing.assert_allclose(o.at(20 * MS).T, screw(0.5))
    o.add(100 * MS, screw(0.1), "odom", "base_footprint")  # another child frame: afresh
    assert len(o) == 1 and o.child == "base_footprint"
    o.add(o.keep_ns * 3, screw(0.0), "odom", "base_footprint")
    o.add(0, screw(0.0), "odom", "base_footprint")  # more than keep_ns back: the clock jumped, afresh
    assert len(o) == 1
    long = Odometry(keep_ns=1000 * MS)
    for s in range(0, 5001, 100):
        long.add(s * MS, screw(s / 1000.0), "odom", "base_link")
    assert len(long) == 11 and long.at(3999 * MS) is None  # only the last second kept


def test_tracking_moves_the_last_pose_by_the_odometry():
    """With odometry covering both stamps, a pair starts from the last pose moved by the odometry's motion
    (origin odometry), before the constant-velocity prediction, and also right after a placement (no velocity
    needed: no placing again); without it (not covered, another frame), as before."""
    def turning(t: float) -> np.ndarray:  # speeding up and turning harder: no constant velocity
        return screw(t, np.array([1.0 + 4.0 * t, 0.0, 0.0, 0.0, 0.0, 0.5 + t]))

    T_map_odom = screw(1.0, np.array([30.0, -12.0, 0.0, 0.0, 0.0, 2.0]))  # the odometry frame in the map
    t = Tracker()
    for s in range(0, 2001, 20):
        t.odometry.add(s * MS, turning(s / 1000.0), "odom", "lidar")
    truth = {s: T_map_odom @ turning(s / 1000.0) for s in (100, 200, 300, 400)}
    assert t.record(truth[100], source_stamp=100 * MS, generation=0, now=1.0, continues=False, placed=True)
    s = t.start(TRACKING, "lidar", "map", now=1.1, stamp=200 * MS)  # right after a placement: tracked, not placed
    assert s.origin == "odometry" and s.origin in TRACKED
    np.testing.assert_allclose(s.T, truth[200], atol=1e-6)
    assert t.record(truth[200], source_stamp=200 * MS, generation=0, now=1.2,
                    continues=motion_continues(s.origin, jumped=False))
    assert t.record(truth[300], source_stamp=300 * MS, generation=0, now=1.3)
    s = t.start(TRACKING, "lidar", "map", now=1.4, stamp=400 * MS)
    np.testing.assert_allclose(s.T, truth[400], atol=1e-6)
    # the constant-velocity prediction from the last two poses misses where the odometry does not
    assert np.linalg.norm(t.predicted(400 * MS)[:3, 3] - truth[400][:3, 3]) > 0.05
    assert t.start(TRACKING, "velodyne", "map", now=1.4, stamp=400 * MS).origin == "predicted"  # other frame
    assert t.start(TRACKING, "lidar", "map", now=1.4, stamp=2500 * MS).origin == "predicted"  # not covered
    assert t.start(TRACKING, "lidar", "map", now=1.4).origin == "last_result"  # no stamp (pair mode)
    t.reset()  # forgets the pose, keeps the odometry
    assert t.start(TRACKING, "lidar", "map", now=1.5, stamp=400 * MS).origin == "none" and len(t.odometry) > 0
    assert not motion_continues("odometry", jumped=True) and motion_continues("odometry", jumped=False)


def test_map_odometry_needs_map_mode():
    from genreg_core.errors import ConfigError
    from genreg_ros.config import MapParams

    with pytest.raises(ConfigError, match="map.odometry needs map.enabled"):
        NodeConfig(map=MapParams(odometry=True))
    assert NodeConfig(map=MapParams(enabled=True, odometry=True)).map.odometry


def map_to_odom(stamp_ms: int, x: float) -> TransformStamped:
    msg = TransformStamped(header=Header(stamp=Time(sec=stamp_ms // 1000, nanosec=(stamp_ms % 1000) * MS),
                                         frame_id="map"), child_frame_id="odom")
    msg.transform.translation.x = x
    return msg


def test_map_to_odom_is_post_dated_and_repeated_until_forgotten():
    m = MapToOdom(200 * MS, 0.5)  # transform_tolerance 0.2 s, transform_publish_period 0.5 s
    assert m.again(100.0) is None  # nothing to repeat yet
    first = m.fresh(map_to_odom(10_000, 1.5), now=100.0)
    assert stamp_ns(first.header) == 10_200 * MS
    assert (first.header.frame_id, first.child_frame_id, first.transform.translation.x) == ("map", "odom", 1.5)
    assert m.again(100.4) is None  # sent 0.4 s ago
    repeated = m.again(100.6)
    assert stamp_ns(repeated.header) == 10_800 * MS and repeated.transform == first.transform
    assert m.again(100.9) is None  # the repeat counts as sent
    assert stamp_ns(m.again(101.25).header) == 11_450 * MS
    # a pose of a scan stamped before the last repeat's stamp minus the tolerance: one ns after it, never before
    late = m.fresh(map_to_odom(11_000, 2.0), now=101.3)
    assert stamp_ns(late.header) == 11_450 * MS + 1 and late.transform.translation.x == 2.0
    assert stamp_ns(m.fresh(map_to_odom(11_500, 2.5), now=101.35).header) == 11_700 * MS
    assert m.again(101.9).transform.translation.x == 2.5  # the newest one is repeated
    m.forget()
    assert m.again(200.0) is None
    # after a reset (e.g. the clock went back: a bag replayed again) stamps start afresh
    assert stamp_ns(m.fresh(map_to_odom(1_000, 3.0), now=201.0).header) == 1_200 * MS
    never = MapToOdom(0, 0.0)  # transform_publish_period 0: only with each pose
    assert stamp_ns(never.fresh(map_to_odom(5_000, 0.0), now=1.0).header) == 5_000 * MS
    assert never.again(1e6) is None
