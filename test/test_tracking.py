"""Initial guesses and tracking of register_node (`genreg_ros.tracking`): pure, no rclpy."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np

from genreg_ros.config import NodeConfig
from genreg_ros.tracking import Tracker


def shift(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


PARAM = (5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # initial_guess parameter: x 5 m
PLAIN = NodeConfig(initial_guess_timeout=5.0)
TRACKING = NodeConfig(initial_guess_timeout=5.0, use_last_result_as_guess=True, initial_guess=PARAM)


def test_policy_and_tracking_need_no_rclpy():
    code = ("import sys, genreg_ros.policy, genreg_ros.tracking\n"
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
