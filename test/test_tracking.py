"""Initial guesses and tracking of register_node (`genreg_ros.tracking`) and map mode's localisation state
(`genreg_ros.map_state`): pure, no rclpy."""

from __future__ import annotations

import subprocess
import sys
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from genreg_core.errors import ConfigError
from genreg_ros import map_state
from genreg_ros.config import MapParams, NodeConfig
from genreg_ros.map_state import GLOBAL, LOST, Localization, scan_start
from genreg_ros.policy import judge
from genreg_ros.tracking import MAX_EXTRAPOLATION, Start, Tracker, motion_continues


def shift(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


PARAM = (5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # initial_guess parameter: x 5 m
PLAIN = NodeConfig(initial_guess_timeout=5.0)
TRACKING = NodeConfig(initial_guess_timeout=5.0, use_last_result_as_guess=True, initial_guess=PARAM)


def test_policy_and_tracking_need_no_rclpy():
    code = ("import sys, genreg_ros.policy, genreg_ros.tracking, genreg_ros.map_state\n"
            "assert not [m for m in sys.modules if m.split('.')[0] == 'rclpy']\n")
    run = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]


def test_no_guess_then_the_parameter():
    t = Tracker()
    s = t.start(PLAIN, "lidar", "map", now=0.0)
    assert (s.T, s.origin, s.discarded) == (None, "none", "")
    s = t.start(NodeConfig(initial_guess=PARAM), "lidar", "map", now=0.0)
    assert s.origin == "parameter" and s.T[0, 3] == 5.0


def test_a_topic_guess_overrides_the_parameter_until_it_expires():
    t = Tracker()
    t.set_guess(shift(1.0), "map", "lidar", "initial_guess", now=10.0)
    config = NodeConfig(initial_guess_timeout=5.0, initial_guess=PARAM)
    s = t.start(config, "lidar", "map", now=14.9)
    assert s.origin == "initial_guess" and s.T[0, 3] == 1.0 and not s.discarded
    s = t.start(config, "lidar", "map", now=15.1)
    assert (s.origin, s.discarded) == ("parameter", "expired") and s.T[0, 3] == 5.0
    assert s.note == "initial_guess guess expired (5.1 s > initial_guess_timeout 5.0 s)"
    assert t.guess is None and t.start(config, "lidar", "map", now=15.2).discarded == ""  # discarded once
    t.set_guess(shift(2.0), "map", None, "initialpose", now=0.0)  # timeout 0: never expires
    assert t.start(NodeConfig(initial_guess_timeout=0.0), "lidar", "map", now=1e6).origin == "initialpose"


def test_a_guess_for_other_frames_is_discarded_with_a_note():
    t = Tracker()
    t.set_guess(shift(1.0), "odom", "lidar", "initial_guess", now=0.0)
    s = t.start(PLAIN, "lidar", "map", now=1.0)
    assert (s.T, s.origin, s.discarded) == (None, "none", "initial_guess_frames")
    assert s.note == "initial_guess guess ignored: it maps lidar into 'odom', the pair maps 'lidar' into 'map'"
    assert t.guess is None
    t.set_guess(shift(1.0), "map", "camera", "initial_guess", now=2.0)
    assert t.start(PLAIN, "lidar", "map", now=3.0).discarded == "initial_guess_frames"
    t.set_guess(shift(1.0), "map", None, "initialpose", now=4.0)  # initialpose: any child frame
    assert t.start(PLAIN, "lidar", "map", now=5.0).origin == "initialpose"


def test_tracking_uses_the_last_result_unless_a_newer_guess_arrived():
    t = Tracker()
    assert t.start(TRACKING, "lidar", "map", now=0.0).origin == "parameter"  # nothing tracked yet
    assert t.record(shift(1.0), source_stamp=100, generation=t.generation, now=1.0)
    s = t.start(TRACKING, "lidar", "map", now=1.5)
    assert s.origin == "last_result" and s.T[0, 3] == 1.0
    assert t.start(PLAIN, "lidar", "map", now=1.5).origin == "none"  # tracking off: the result is not used
    t.set_guess(shift(3.0), "map", "lidar", "initial_guess", now=2.0)  # newer than the result: wins
    assert t.start(TRACKING, "lidar", "map", now=2.5).origin == "initial_guess"
    assert t.record(shift(4.0), source_stamp=200, generation=t.generation, now=3.0)  # newer than the guess
    s = t.start(TRACKING, "lidar", "map", now=3.5)
    assert s.origin == "last_result" and s.T[0, 3] == 4.0


def test_tracking_moves_the_last_result_on_at_the_velocity_of_the_last_two():
    """Map mode passes the scan's stamp: the last pose goes on at the last two poses' velocity, scaled by the
    stamps (1 m per 100 ms here), capped at MAX_EXTRAPOLATION intervals; a pose that did not start from the
    last result (found without a guess, or from a topic guess), or left its prediction, starts the motion
    afresh."""
    t = Tracker()
    g = t.generation
    ms = 1_000_000  # ns
    assert t.start(TRACKING, "lidar", "map", now=0.0, stamp=100 * ms).origin == "parameter"  # nothing kept yet
    assert t.record(shift(1.0), source_stamp=100 * ms, generation=g, now=1.0, continues=False)  # placed globally
    s = t.start(TRACKING, "lidar", "map", now=1.5, stamp=200 * ms)  # one pose: no velocity yet
    assert s.origin == "last_result" and s.T[0, 3] == 1.0 and t.predicted(200 * ms) is None
    assert t.record(shift(2.0), source_stamp=200 * ms, generation=g, now=2.0)
    s = t.start(TRACKING, "lidar", "map", now=2.5, stamp=300 * ms)
    assert s.origin == "predicted" and s.T[0, 3] == pytest.approx(3.0)
    assert t.start(TRACKING, "lidar", "map", now=2.5, stamp=250 * ms).T[0, 3] == pytest.approx(2.5)
    s = t.start(TRACKING, "lidar", "map", now=2.5)  # no stamp: the last result as kept
    assert s.origin == "last_result" and s.T[0, 3] == 2.0
    far = 200 * ms + int(10 * MAX_EXTRAPOLATION) * 100 * ms  # a long gap: at most MAX_EXTRAPOLATION intervals
    assert t.predicted(far)[0, 3] == pytest.approx(2.0 + MAX_EXTRAPOLATION)
    s = t.start(TRACKING, "lidar", "map", now=2.5, stamp=150 * ms)  # before the last result: not extrapolated back
    assert s.origin == "last_result" and s.T[0, 3] == 2.0
    assert t.record(shift(2.0), source_stamp=200 * ms, generation=g, now=2.6)  # the same stamp again
    assert t.predicted(300 * ms)[0, 3] == pytest.approx(3.0)  # ... keeps the velocity
    # a kidnap: the pose found from the prediction lies beyond tracking's reach of it
    assert t.record(shift(40.0), source_stamp=300 * ms, generation=g, now=3.0,
                    continues=motion_continues("predicted", jumped=True))
    assert t.predicted(400 * ms) is None  # the jump is no velocity
    assert t.start(TRACKING, "lidar", "map", now=3.5, stamp=400 * ms).T[0, 3] == 40.0
    t.reset()
    assert t.predicted(400 * ms) is None
    assert t.start(TRACKING, "lidar", "map", now=4.0, stamp=500 * ms).origin == "parameter"  # nothing tracked
    # what a result continues: from the last pose as kept, however far it moved (a fast vehicle's second scan,
    # beyond reach of the pose before: its motion is the velocity); from a prediction, only within reach of it;
    # nothing found without a guess or from a topic guess
    assert motion_continues("last_result", jumped=True) and motion_continues("predicted", jumped=False)
    assert not motion_continues("predicted", jumped=True)
    assert not any(motion_continues(origin, jumped=False) for origin in ("none", "initialpose", "initial_guess"))


def test_a_pose_placed_without_a_guess_is_placed_again_for_its_velocity():
    """With stamps (map.predict_motion), the pair after a placement without a guess is placed again (once), and
    the two placements give the velocity; without stamps, or once the second placement missed, it is tracked
    from the placement as before. A pose tracked from a topic guess is not placed again."""
    ms = 1_000_000  # ns
    t = Tracker()
    g = t.generation
    assert t.record(shift(1.0), source_stamp=100 * ms, generation=g, now=1.0, continues=False, placed=True)
    s = t.start(TRACKING, "lidar", "map", now=1.1, stamp=200 * ms)
    assert s.origin == "none" and s.T is None  # placed again: a vehicle may have moved on 2 m in 100 ms
    # the pair after it, while that one is being placed: tracked from the placement, not placed a third time
    assert t.start(TRACKING, "lidar", "map", now=1.2, stamp=300 * ms).origin == "last_result"
    assert t.record(shift(3.0), source_stamp=200 * ms, generation=g, now=1.3, continues=False, placed=True)
    assert t.predicted(300 * ms)[0, 3] == pytest.approx(5.0)  # 2 m per 100 ms, from the two placements
    s = t.start(TRACKING, "lidar", "map", now=1.4, stamp=300 * ms)
    assert s.origin == "predicted" and s.T[0, 3] == pytest.approx(5.0)
    assert t.record(shift(5.0), source_stamp=300 * ms, generation=g, now=1.5)  # tracked on: placed no more
    assert t.start(TRACKING, "lidar", "map", now=1.6, stamp=400 * ms).origin == "predicted"

    missed = Tracker()  # the second placement missed (not recorded): tracked from the first
    assert missed.record(shift(1.0), source_stamp=100 * ms, generation=0, now=1.0, continues=False, placed=True)
    assert missed.start(TRACKING, "lidar", "map", now=1.1, stamp=200 * ms).origin == "none"
    s = missed.start(TRACKING, "lidar", "map", now=1.2, stamp=300 * ms)
    assert s.origin == "last_result" and s.T[0, 3] == 1.0

    unstamped = Tracker()  # map.predict_motion off: no velocity to learn
    assert unstamped.record(shift(1.0), source_stamp=100 * ms, generation=0, now=1.0, continues=False, placed=True)
    assert unstamped.start(TRACKING, "lidar", "map", now=1.1).origin == "last_result"

    clicked = Tracker()  # tracked from an operator's pose: not a placement
    assert clicked.record(shift(1.0), source_stamp=100 * ms, generation=0, now=1.0, continues=False)
    assert clicked.start(TRACKING, "lidar", "map", now=1.1, stamp=200 * ms).origin == "last_result"
    clicked.record(shift(1.0), source_stamp=200 * ms, generation=0, now=1.2, continues=False, placed=True)
    clicked.reset()  # forgets the placement
    assert clicked.start(TRACKING, "lidar", "map", now=1.3, stamp=300 * ms).origin == "parameter"


def test_only_an_initialpose_start_is_rough():
    """An operator's click (`initialpose`) may be metres off: its start is rough (the localiser searches as far);
    a guess on `initial_guess`, the last pose and the pose moved on from it are not."""
    tracker = Tracker()
    tracker.set_guess(shift(2.0), "map", None, "initialpose", now=1.0)
    clicked = tracker.start(TRACKING, "lidar", "map", now=1.1, tracking=True, parameter=False)
    assert clicked.origin == "initialpose" and clicked.rough
    assert tracker.record(shift(0.1), source_stamp=100, generation=0, now=1.2, continues=False)
    tracked = tracker.start(TRACKING, "lidar", "map", now=1.3, tracking=True, parameter=False)
    assert tracked.origin == "last_result" and not tracked.rough
    tracker.set_guess(shift(2.0), "map", "lidar", "initial_guess", now=1.4)
    given = tracker.start(TRACKING, "lidar", "map", now=1.5, tracking=True, parameter=False)
    assert given.origin == "initial_guess" and not given.rough
    assert not Start(None, "none").rough


def test_in_state_global_a_tracked_start_is_dropped_and_a_topic_guess_kept():
    """Global and lost localise without a guess: the last pose, moved on or not, is not used there (unless
    `keep`)."""
    for origin in ("last_result", "predicted"):
        step, start = scan_start(map_state.Step(GLOBAL, 3), Start(shift(1.0), origin))
        assert (step.mode, step.generation, start.T, start.origin) == (GLOBAL, 3, None, "none")
    step, start = scan_start(map_state.Step(GLOBAL, 3), Start(shift(1.0), "initialpose"))
    assert step.mode == map_state.TRACKING and start.origin == "initialpose"
    # a map with the place index keeps the last pose while lost: its unsure track is searched globally anyway
    step, start = scan_start(map_state.Step(GLOBAL, 3), Start(shift(1.0), "predicted"), keep=True)
    assert step.mode == map_state.TRACKING and start.origin == "predicted" and start.T[0, 3] == 1.0


def test_a_pose_found_without_a_guess_needs_relocalize_confidence():
    """map.relocalize_confidence holds back a relocalised pose below it; a tracked pose, or the setting at 0,
    needs min_confidence alone."""
    result = SimpleNamespace(fitness=0.9, confidence=0.7, unconstrained=())
    strict = NodeConfig(map=MapParams(relocalize_confidence=0.8))
    verdict = judge(result, strict, relocalized=True)
    assert not verdict.publish and verdict.reason == "low_confidence_rejected"
    assert verdict.why == "confidence 0.700 < map.relocalize_confidence 0.8 (relocalised)"
    assert judge(result, strict).publish and judge(result, NodeConfig(), relocalized=True).publish
    assert judge(SimpleNamespace(fitness=0.9, confidence=0.85, unconstrained=()), strict, relocalized=True).publish


def test_an_older_pairs_result_never_replaces_a_newer_one():
    t = Tracker()
    g = t.generation
    assert t.record(shift(2.0), source_stamp=200, generation=g, now=1.0)
    assert not t.record(shift(1.0), source_stamp=100, generation=g, now=2.0)  # finished later, taken earlier
    assert t.last_result[0, 3] == 2.0
    assert t.record(shift(3.0), source_stamp=200, generation=g, now=3.0)  # the same stamp: the newer result


def test_reset_forgets_everything_and_ignores_results_of_pairs_taken_before_it():
    t = Tracker()
    g = t.generation
    t.record(shift(1.0), 100, g, now=1.0)
    t.set_guess(shift(2.0), "map", "lidar", "initial_guess", now=1.0)
    t.reset()
    assert t.last_result is None and t.guess is None and t.generation == g + 1
    assert t.start(TRACKING, "lidar", "map", now=2.0).origin == "parameter"
    assert not t.record(shift(5.0), 300, g, now=3.0)  # its pair was taken before the reset
    assert t.last_result is None
    assert t.record(shift(6.0), 50, t.generation, now=3.0)  # stamps start over after a reset (bag loop)


def test_concurrent_records_keep_the_newest_stamp():
    t = Tracker()
    g = t.generation

    def worker(k: int) -> None:
        for stamp in range(k, 2000, 4):
            t.record(shift(float(stamp)), stamp, g, now=float(stamp))

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert t.last_result[0, 3] == 1999.0


# ----------------------------------------------------------------------------- map mode
MAP = NodeConfig(initial_guess=PARAM)  # map mode ignores the initial_guess parameter


class StubLocalizer:
    """MapLocalizer's interface: `localize(scan, initial_guess)` -> a result with `transformation` and a
    calibrated `confidence`. The scan is its true pose (4x4); a guess within 0.5 m of it, or no guess on an
    on-map pose (|x| < 10 m), is placed confidently; anything else gets confidence 0.1 at the guess."""

    def __init__(self) -> None:
        self.guesses: list[np.ndarray | None] = []

    def localize(self, scan: np.ndarray, initial_guess: np.ndarray | None = None):
        self.guesses.append(initial_guess)
        on_map = abs(scan[0, 3]) < 10.0
        near = initial_guess is None or np.linalg.norm(initial_guess[:3, 3] - scan[:3, 3]) < 0.5
        ok = on_map and near
        T = scan if ok else (initial_guess if initial_guess is not None else np.eye(4))
        return SimpleNamespace(transformation=T, confidence=0.95 if ok else 0.1, fitness=0.9, unconstrained=())


class MapDriver:
    """The node's map-mode steps for one scan, without ROS: step, start, localise, judge, record, update."""

    def __init__(self, lost_after: int = 2) -> None:
        self.tracker, self.state, self.loc = Tracker(), Localization(lost_after), StubLocalizer()
        self.stamp = 0

    def scan(self, pose: np.ndarray, now: float = 0.0) -> tuple[str, bool]:
        """(the state the scan is reported in, whether its pose was published)."""
        self.stamp += 1
        generation = self.tracker.generation
        step, start = scan_start(self.state.step(), self.tracker.start(MAP, "camera", "map", now, tracking=True,
                                                                          parameter=False))
        result = self.loc.localize(pose, initial_guess=start.T)
        verdict = judge(result, MAP)
        hit = verdict.publish  # as the node: a miss is a scan whose pose is not published
        if verdict.publish:
            self.tracker.record(result.transformation, self.stamp, generation, now)
        return self.state.update(step, hit), verdict.publish

    def relocalize(self) -> None:
        self.tracker.reset()
        self.state.relocalize()


def test_map_state_global_tracking_lost_global():
    d = MapDriver(lost_after=2)
    assert d.state.state == GLOBAL
    assert d.scan(shift(1.0)) == (GLOBAL, True)  # the first scan: no guess
    assert d.loc.guesses[-1] is None and d.state.state == map_state.TRACKING
    assert d.scan(shift(1.2)) == (map_state.TRACKING, True)  # from the last accepted pose
    assert np.allclose(d.loc.guesses[-1], shift(1.0))
    assert d.scan(shift(5.0)) == (map_state.TRACKING, False)  # kidnapped: the guess is 3.8 m off, one miss
    assert d.scan(shift(5.1)) == (LOST, False)  # a second miss: lost
    assert np.allclose(d.loc.guesses[-1], shift(1.2)), "a rejected pose is never the next guess"
    assert d.scan(shift(5.2)) == (GLOBAL, True)  # relocalised without a guess
    assert d.loc.guesses[-1] is None
    assert d.scan(shift(5.3)) == (map_state.TRACKING, True)


def test_off_map_scans_publish_nothing_and_stay_lost_until_one_is_placed():
    d = MapDriver(lost_after=3)
    assert d.scan(shift(50.0)) == (GLOBAL, False)  # off the map
    assert d.scan(shift(50.0)) == (GLOBAL, False)
    assert d.scan(shift(50.0)) == (LOST, False)  # the third miss in a row
    assert d.scan(shift(50.0)) == (LOST, False)  # still lost; each is tried globally
    assert all(g is None for g in d.loc.guesses)
    assert d.scan(shift(2.0)) == (GLOBAL, True) and d.state.state == map_state.TRACKING and d.state.misses == 0


def test_a_hit_between_misses_restarts_the_count():
    d = MapDriver(lost_after=2)
    d.scan(shift(1.0))
    assert d.scan(shift(3.0)) == (map_state.TRACKING, False)
    assert d.scan(shift(1.1)) == (map_state.TRACKING, True)  # back near the last pose
    assert d.scan(shift(3.0)) == (map_state.TRACKING, False)  # one miss again, not two
    assert d.state.state == map_state.TRACKING


def test_relocalize_localises_the_next_scan_globally_and_ignores_scans_taken_before():
    d = MapDriver()
    d.scan(shift(1.0))
    step = d.state.step()
    assert step.mode == map_state.TRACKING
    d.relocalize()
    assert d.state.update(step, hit=True) == map_state.TRACKING and d.state.state == GLOBAL  # stale: no effect
    assert d.state.update(step, hit=False) == map_state.TRACKING and d.state.misses == 0
    assert d.scan(shift(1.1)) == (GLOBAL, True) and d.loc.guesses[-1] is None


def test_a_topic_guess_is_used_in_every_state_and_the_parameter_never():
    d = MapDriver(lost_after=1)
    d.tracker.set_guess(shift(7.1), "map", None, "initialpose", now=0.0)
    assert d.scan(shift(7.0), now=0.5) == (map_state.TRACKING, True)  # RViz's pose: the first scan starts there
    assert np.allclose(d.loc.guesses[-1], shift(7.1))
    assert d.scan(shift(20.0), now=1.0) == (LOST, False)
    d.tracker.set_guess(shift(-3.1), "map", None, "initialpose", now=1.5)  # lost, then a pose from RViz
    assert d.scan(shift(-3.0), now=2.0) == (map_state.TRACKING, True) and np.allclose(d.loc.guesses[-1], shift(-3.1))
    d.relocalize()  # forgets the guess too
    assert d.scan(shift(-3.0), now=2.5) == (GLOBAL, True) and d.loc.guesses[-1] is None


def test_map_settings_are_checked():
    with pytest.raises(ConfigError, match="workers 1"):
        NodeConfig(map=MapParams(enabled=True), workers=2)
    with pytest.raises(ConfigError, match="map.lost_after"):
        MapParams(lost_after=0)
    with pytest.raises(ValueError, match="lost_after"):
        Localization(0)


def test_placement_says_how_a_pose_stands_to_its_start():
    """A pose with no start, or beyond tracking's reach of it, jumped; a pose found without a start (in state
    tracking: placed again to learn the motion), or while no pose was known (step global) beyond reach of its
    start, is a relocalisation; a pose within reach of its start neither left it nor jumped."""
    none, near = Start(None, "none"), Start(shift(1.0), "predicted")
    for mode in (GLOBAL, map_state.TRACKING):
        step = map_state.Step(mode, 0)
        assert map_state.placement(step, none, reached=False) == map_state.Placement(False, True, True)
        assert map_state.placement(step, near, reached=False) == map_state.Placement(True, mode == GLOBAL, True)
        assert map_state.placement(step, near, reached=True) == map_state.Placement(False, False, False)
