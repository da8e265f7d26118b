"""The accept/reject policy of register_node (`genreg_ros.policy`): pure, no rclpy."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from genreg_ros.config import NodeConfig
from genreg_ros.policy import judge

CONFIG = NodeConfig(min_fitness=0.5, min_confidence=0.2, warn_confidence=0.4)


def result(fitness: float = 0.9, confidence: float = 0.9, unconstrained: tuple[str, ...] = ()) -> SimpleNamespace:
    return SimpleNamespace(fitness=fitness, confidence=confidence, unconstrained=unconstrained)


def test_a_good_result_is_published_ok():
    v = judge(result(), CONFIG)
    assert (v.publish, v.reason, v.why, v.low_confidence, v.degenerate) == (True, "", "", False, False)
    assert (v.level, v.message) == ("ok", "published")


def test_low_fitness_is_rejected_before_low_confidence():
    v = judge(result(fitness=0.3, confidence=0.1), CONFIG)
    assert not v.publish and v.reason == "low_fitness" and v.level == "error"
    assert v.why == "fitness 0.300 < min_fitness 0.5" and v.message == "rejected: fitness 0.300 < min_fitness 0.5"
    assert not v.low_confidence  # a rejected result is not also a published low-confidence one


def test_low_confidence_below_min_is_rejected():
    v = judge(result(confidence=0.1), CONFIG)
    assert (v.publish, v.reason, v.level) == (False, "low_confidence_rejected", "error")
    assert v.why == "confidence 0.100 < min_confidence 0.2"


@pytest.mark.parametrize(("confidence", "low"), [(0.2, True), (0.39, True), (0.4, False)])
def test_confidence_between_min_and_warn_is_published_with_a_warning(confidence, low):
    v = judge(result(confidence=confidence), CONFIG)
    assert v.publish and v.low_confidence is low
    assert (v.level, v.message) == (("warn", "published with low confidence") if low else ("ok", "published"))


def test_thresholds_are_inclusive_at_the_limits():
    assert judge(result(fitness=0.5, confidence=0.4), CONFIG).level == "ok"
    assert judge(result(fitness=0.0, confidence=0.0), NodeConfig(min_confidence=0.0, warn_confidence=0.0)).publish


def test_a_degenerate_result_is_a_warn_naming_its_free_directions():
    v = judge(result(unconstrained=("translation along x", "rotation about z")), CONFIG)
    assert v.publish and v.degenerate and v.level == "warn"
    assert v.message == "degenerate: translation along x; rotation about z (target frame); published"
    v = judge(result(confidence=0.1, unconstrained=("translation along x",)), CONFIG)
    assert v.level == "error" and v.message.startswith("degenerate: translation along x (target frame); rejected:")
    assert not judge(SimpleNamespace(fitness=1.0, confidence=1.0), CONFIG).degenerate  # no such attribute

