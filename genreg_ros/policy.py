"""Whether register_node publishes a registration result, and what its `registration_status` says.

Pure Python (no rclpy): `judge(result, config)` reads the result's fitness, confidence and unconstrained
directions and the thresholds min_fitness, min_confidence and warn_confidence, and returns a `Verdict`.
Rejected (not published): fitness below min_fitness (`low_fitness`), else confidence below min_confidence
(`low_confidence_rejected`; in map mode, while no pose is known, a pose not within tracking's reach of the last
one also below `map.relocalize_confidence`). Published with a warning: confidence below warn_confidence. A result whose
geometry leaves directions unconstrained (the core's `unconstrained`) is published as WARN, `degenerate`.
In map mode the message starts with the scan's localisation state (`global: published`, `lost: rejected: ...`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from genreg_ros.config import NodeConfig

if TYPE_CHECKING:
    from genreg_core.result import RegistrationResult

Level = Literal["ok", "warn", "error"]  # the registration_status level (DiagnosticStatus OK, WARN, ERROR)


@dataclass(frozen=True)
class Verdict:
    """What to do with one result: publish it or not, why not, and its status level and message."""

    publish: bool
    reason: str  # the failed.<reason> count of a rejected result ("" when published)
    why: str  # one line: why it was rejected ("" when published)
    low_confidence: bool  # published, below warn_confidence
    unconstrained: tuple[str, ...]  # the directions the geometry leaves free (degenerate when any)
    localization: str = ""  # map mode: the scan's state (global, tracking, lost; genreg_ros.map_state), else ""
    jumped: bool = False  # map mode: the pose was not tracked from its start (none, or beyond tracking's reach)

    @property
    def degenerate(self) -> bool:
        return bool(self.unconstrained)

    @property
    def level(self) -> Level:
        return "error" if not self.publish else "warn" if self.low_confidence or self.degenerate else "ok"

    @property
    def message(self) -> str:
        text = f"rejected: {self.why}" if not self.publish else \
            "published with low confidence" if self.low_confidence else "published"
        text = f"degenerate: {'; '.join(self.unconstrained)} (target frame); {text}" if self.degenerate else text
        return f"{self.localization}: {text}" if self.localization else text


def judge(result: RegistrationResult, config: NodeConfig, relocalized: bool = False) -> Verdict:
    """The verdict on `result` (a RegistrationResult: fitness, confidence, unconstrained) under the
    thresholds of `config`; `relocalized`: a map-mode pose found while no pose was known, not within tracking's
    reach of the last one (`map.relocalize_confidence`)."""
    unconstrained = tuple(getattr(result, "unconstrained", ()) or ())
    reason, why = "", ""
    if result.fitness < config.min_fitness:
        reason, why = "low_fitness", f"fitness {result.fitness:.3f} < min_fitness {config.min_fitness}"
    elif result.confidence < config.min_confidence:
        reason, why = "low_confidence_rejected", \
            f"confidence {result.confidence:.3f} < min_confidence {config.min_confidence}"
    elif relocalized and result.confidence < config.map.relocalize_confidence:
        reason, why = "low_confidence_rejected", (f"confidence {result.confidence:.3f} < map.relocalize_confidence "
                                                  f"{config.map.relocalize_confidence} (relocalised)")
    low_confidence = not reason and result.confidence < config.warn_confidence
    return Verdict(not reason, reason, why, low_confidence, unconstrained)
