"""register_node's map mode: the localisation state of scans placed in a prior map.

Pure Python (no rclpy), thread-safe. In map mode (`map.enabled`) every source scan is localised in the
map (`genreg_core.localization.MapLocalizer`), either globally (no guess) or from a guess. The state says
which the next scan gets:
- `global`: no pose is known (start-up, a new map frame, `~/relocalize`, `~/reset`, a time jump): the next
  scan is localised without a guess;
- `tracking`: the last accepted pose is the guess of the next scan;
- `lost`: `map.lost_after` scans in a row missed (a miss: no pose published, i.e. the confidence is
  below `min_confidence`, the fitness below `min_fitness`, or it failed): the next scan is localised
  without a guess, as in `global`; with the place index (LiDAR maps) from the last accepted pose, whose
  unsure track is searched for in the whole map as well (`scan_start`'s `keep`).
A pose found while no pose is known (global and lost), or placed again without a guess (in tracking, the scan
after a placement: `genreg_ros.tracking`), is published only at `map.relocalize_confidence` (`policy.judge`'s
`relocalized`).
A guess from a topic (`initialpose`, `initial_guess`) is used in every state (`genreg_ros.tracking`).
A hit in any state leads to `tracking`; misses while `global` or `tracking` count towards `lost`.

`Localization.update` returns the state a scan is reported in (`registration_status` key `localization`):
`lost` if the scan missed and tracking is lost after it, else how the scan was localised (`global` or
`tracking`). `relocalize` starts a new generation: the outcome of a scan taken before it changes nothing.
`scan_start` combines the state's step with the tracker's start (`Tracker.start(..., tracking=True,
parameter=False)`): the initial_guess parameter is not used in map mode.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from genreg_ros.tracking import TRACKED, Start

GLOBAL, TRACKING, LOST = "global", "tracking", "lost"
STATES = (GLOBAL, TRACKING, LOST)


@dataclass(frozen=True)
class Step:
    """How to localise one scan: `mode` global (no guess) or tracking (from a guess), and the generation to
    hand back to `Localization.update`."""

    mode: str
    generation: int


class Localization:
    """The map-mode state machine of one node: global -> tracking -> lost -> global."""

    def __init__(self, lost_after: int = 2) -> None:
        if lost_after < 1:
            raise ValueError(f"lost_after must be >= 1, got {lost_after}")
        self.lost_after = lost_after
        self._lock = threading.Lock()
        self._state = GLOBAL
        self._misses = 0
        self._generation = 0

    @property
    def state(self) -> str:
        """global, tracking or lost."""
        return self._state

    @property
    def misses(self) -> int:
        """Scans in a row that missed since the last hit (or relocalisation)."""
        return self._misses

    def step(self) -> Step:
        """How the next scan is localised: tracking only in state tracking, else global."""
        with self._lock:
            return Step(TRACKING if self._state == TRACKING else GLOBAL, self._generation)

    def update(self, step: Step, hit: bool, lost_after: int | None = None) -> str:
        """Record the outcome of a scan localised as `step` (hit: its pose was published) and
        return the state it is reported in. `lost_after` (None: the constructor's) may change at run time."""
        with self._lock:
            if lost_after is not None:
                self.lost_after = lost_after
            if step.generation != self._generation:  # relocalised meanwhile: this outcome is stale
                return step.mode
            if hit:
                self._state, self._misses = TRACKING, 0
                return step.mode
            self._misses += 1
            if self._misses >= self.lost_after:
                self._state = LOST
            return LOST if self._state == LOST else step.mode

    def relocalize(self) -> None:
        """Forget the pose: the next scan is localised globally; outcomes of scans taken before are ignored."""
        with self._lock:
            self._state, self._misses = GLOBAL, 0
            self._generation += 1


@dataclass(frozen=True)
class Placement:
    """How a scan's pose stands to the start it was localised from (`placement`)."""

    left: bool  # beyond tracking's reach of its start: found elsewhere, by a search (`motion_continues`)
    relocalized: bool  # found while no pose was known, without a start or having left it, or placed without a
    # guess again to learn the motion (`Tracker.start`): judged as a relocalisation (`policy.judge`)
    jumped: bool  # not tracked from its start: it had none, or left it (registration_status `jumped`)


def placement(before: Step, start: Start, reached: bool) -> Placement:
    """The placement of a pose localised in the state `before` from `start`; `reached`: the pose lies within
    tracking's reach of `start.T` (`MapLocalizer.within_reach`; not read without a start)."""
    left = start.T is not None and not reached
    jumped = start.T is None or left
    return Placement(left, jumped and (before.mode == GLOBAL or start.T is None), jumped)


def scan_start(step: Step, start: Start, keep: bool = False) -> tuple[Step, Start]:
    """How a scan is localised: `start` is the tracker's (a topic guess, else the last accepted pose, else
    none). A topic guess is used in every state; the last pose in state tracking, and in state lost when
    `keep` (a map with the place index, whose localisation from an unsure guess also searches the whole map;
    other maps, and global and lost without `keep`, localise without a guess). The returned step's mode is
    tracking when there is a guess, else global."""
    if step.mode == GLOBAL and start.origin in TRACKED and not keep:
        start = Start(None, "none", start.discarded, start.note)
    return Step(GLOBAL if start.T is None else TRACKING, step.generation), start
