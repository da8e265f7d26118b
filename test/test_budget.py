"""The node's latency budget (`genreg_ros.budget`): which pairs go light, and what light leaves out."""

from __future__ import annotations

import time

import numpy as np

from genreg_core.config import SCENE_REGISTRATION
from genreg_core.data import RGBDSequence
from genreg_core.metrics import rotation_error_deg, translation_error
from genreg_core.registration import Registrar
from genreg_ros import budget
from genreg_ros.budget import LatencyBudget, light_config


def test_light_config_switches_off_the_work_a_confident_answer_does_not_need():
    light = light_config(SCENE_REGISTRATION, 1500)
    assert light.passes == 1 and light.pdsac.modes_below == 0.0
    assert light.refine.guard_below == 0.0 and light.refine.fine_fraction == 1.0 and light.refine.num_points == 1500
    # everything else as the full settings
    assert light.refine.method == SCENE_REGISTRATION.refine.method and light.pdsac.sample_size == 4
    assert light_config(SCENE_REGISTRATION, 10**6).refine.num_points == SCENE_REGISTRATION.refine.num_points


def test_plan_is_full_until_a_pair_would_be_late():
    b = LatencyBudget()
    light, cfg = b.plan(0.5, SCENE_REGISTRATION, 0.075, 1500)
    assert light  # older than the budget already
    b = LatencyBudget()
    assert b.plan(0.0, SCENE_REGISTRATION, 0.075, 1500) == (False, SCENE_REGISTRATION)  # nothing learnt yet
    b.record(False, 0.060)
    assert not b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[0]  # 10 + 60 ms fits
    light, cfg = b.plan(0.020, SCENE_REGISTRATION, 0.075, 1500)  # 20 + 60 ms does not
    assert light and cfg == light_config(SCENE_REGISTRATION, 1500)
    assert b.plan(0.020, SCENE_REGISTRATION, 0.075, 1500)[1] is cfg  # one light object per settings object
    assert b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[1] is SCENE_REGISTRATION  # full: the settings given
    assert not b.plan(10.0, SCENE_REGISTRATION, 0.0, 1500)[0]  # budget 0: off
    b.record(True, 5.0)  # light registrations teach nothing
    assert b.expected_full == 0.060


def test_the_expectation_is_a_high_quantile_of_the_recent_full_registrations():
    """Two slow registrations in the last twenty make a pair that would fit the mean go light: the budget holds
    nine pairs in ten, not the average one; older registrations leave the window."""
    b = LatencyBudget()
    assert not b.plan(0.0, SCENE_REGISTRATION, 0.075, 1500)[0]  # a full registration starts now (no probe due)
    for seconds in [0.040] * 18 + [0.090] * 2:
        b.record(False, seconds)
    assert np.mean([0.040] * 18 + [0.090] * 2) + 0.010 < 0.075  # the mean would fit
    assert b.expected_full == 0.090 and b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[0]
    for _ in range(budget.WINDOW):
        b.record(False, 0.040)
    assert b.expected_full == 0.040 and not b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[0]


def test_a_full_probe_lets_the_expectation_follow_the_load_down(monkeypatch):
    b = LatencyBudget()
    b.record(False, 0.200)  # learnt under heavy load
    b.plan(0.0, SCENE_REGISTRATION, 0.075, 1500)  # a full registration starts now
    assert b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[0]
    monkeypatch.setattr(budget, "PROBE_S", 0.0)
    assert not b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[0]  # the probe: full again
    for _ in range(30):
        b.record(False, 0.040)
    monkeypatch.setattr(budget, "PROBE_S", 2.0)
    time.sleep(0.001)
    assert not b.plan(0.010, SCENE_REGISTRATION, 0.075, 1500)[0] and abs(b.expected_full - 0.040) < 0.005


def test_a_light_registration_is_right_and_confident_on_consecutive_frames():
    """The shipped scene model on validation frames 1 apart: light and full agree with the recorded poses."""
    seq = RGBDSequence.redkitchen()
    reg = Registrar.from_checkpoint("7scenes", light_config(SCENE_REGISTRATION, 1500))
    for frame in (850, 900, 950):
        result = reg.register(seq.points(frame + 1, stride=2), seq.points(frame, stride=2))
        truth = seq.relative_pose(frame + 1, frame)
        assert rotation_error_deg(result.transformation[:3, :3], truth[:3, :3]) < 2.0
        assert translation_error(result.transformation[:3, 3], truth[:3, 3]) < 0.05
        assert result.confidence >= 0.5 and "modes" not in result.timings and result.passes == 1
        assert np.isfinite(result.covariance).all()


def test_warm_up_changes_no_setting_and_no_later_result():
    """A worker registers `warm_up_pair` before it reports ready: its known motion is recovered, and the
    registrar's settings and its next result are those of a registrar that never warmed up."""
    from genreg_core.registration import warm_up_pair

    source, target = warm_up_pair(5000)
    cold = Registrar.from_checkpoint("7scenes", SCENE_REGISTRATION)
    first = cold.register(source, target)
    warm = Registrar(cold.model, SCENE_REGISTRATION, cold.calibration)
    warm.warm_up()
    assert warm.config == SCENE_REGISTRATION
    again = warm.register(source, target)
    np.testing.assert_array_equal(again.transformation, first.transformation)
    angle = np.radians(10.0)
    assert abs(np.arctan2(first.transformation[1, 0], first.transformation[0, 0]) - angle) < np.radians(1.0)
    assert np.allclose(first.transformation[:3, 3], (0.2, -0.1, 0.05), atol=0.02)
