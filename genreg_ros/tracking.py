"""Where register_node starts each registration: initial guesses and tracking.

Pure Python (no rclpy), thread-safe; times are time.monotonic seconds passed in by the caller. The start of
a pair's registration (`Tracker.start`) is, in this order of preference:
- the newest guess from a topic (`initial_guess` or `initialpose`), unless it expired (older than
  initial_guess_timeout, 0: never) or names other frames than the pair's (both discard it), or, when
  tracking, a result newer than it exists;
- the last result (use_last_result_as_guess), recorded only for pairs taken since the last reset and never
  replaced by the result of an older pair (several workers finish out of order); given the pair's source
  stamp (map mode) and odometry of the pair's source frame covering both stamps (`map.odometry`,
  `genreg_ros.odometry`), moved by the odometry's motion between them (origin `odometry`, whatever placed the
  last result); else, given the stamp and `map.predict_motion`, moved on at the velocity of the last two results (origin
  `predicted`, `Tracker.predicted`); a pose placed by a search (found without a guess, or beyond tracking's
  reach of its start: a jump) has no velocity yet, so the pair after it is placed without a guess again
  (once; origin `none`) and the two placements give the velocity: a vehicle placed while it moves is not
  tracked from where it was a scan ago, where a road or a corridor may hold the track short of its place
  with nothing to tell (`Tracker.start`);
- the initial_guess parameter;
- none.
`reset` forgets the topic guess and the last result and starts a new generation: a result of a pair taken
before it is not recorded.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from genreg_core.geometry import extrapolate
from genreg_ros.config import NodeConfig
from genreg_ros.odometry import Odometry

ORIGINS = ("none", "parameter", "initial_guess", "initialpose", "last_result", "predicted", "odometry")  # status values
TRACKED = ("last_result", "predicted", "odometry")  # the origins that continue the tracked motion
# the last result is moved on by at most this many times the motion between the last two (a longer gap: a pause
# or a stall, whose motion the last one no longer tells)
MAX_EXTRAPOLATION = 5.0


@dataclass(frozen=True)
class TopicGuess:
    """A guess from a topic: T_target_source, the frames it names (child None: any), its arrival time and
    its topic (initial_guess or initialpose)."""

    T: np.ndarray
    parent: str
    child: str | None
    received: float
    origin: str


@dataclass(frozen=True)
class Start:
    """A pair's start: T_target_source (None: no guess), where it came from (one of ORIGINS), and a topic
    guess discarded on the way ("expired" or "initial_guess_frames", with a one-line note; "" if none)."""

    T: np.ndarray | None
    origin: str
    discarded: str = ""
    note: str = ""

    @property
    def rough(self) -> bool:
        """Whether the guess is an operator's click (`initialpose`), which may be metres off, not a pose tracked
        or computed (`MapLocalizer.localize`'s `rough`)."""
        return self.origin == "initialpose"


def motion_continues(origin: str, jumped: bool) -> bool:
    """Whether a result continues the tracked motion (`Tracker.record`'s `continues`): it started from the last
    result as kept (`last_result`: whatever it moved by is the motion), or from the last result moved on
    (`predicted`, `odometry`) and stayed within reach of that start (`jumped` False); a start the result left (a
    vehicle carried away, an abrupt stop) is no velocity to go on with."""
    return origin == "last_result" or (origin in ("predicted", "odometry") and not jumped)


class Tracker:
    """The topic guess, the last result, the odometry and the reset generation of one node."""

    def __init__(self) -> None:
        self.odometry = Odometry()  # filled by the node's odom subscription (map.odometry); kept over resets
        self._lock = threading.Lock()
        self._guess: TopicGuess | None = None
        self._last_T: np.ndarray | None = None
        self._last_time = -np.inf
        self._last_stamp = -1  # source stamp (ns) of the last result
        self._previous: tuple[np.ndarray, int] | None = None  # the result before it and its stamp
        self._placed = False  # the last result was placed by a search, no velocity known
        self._again = False  # ... and a pair has been started to place it again
        self._generation = 0

    @property
    def generation(self) -> int:
        """Incremented by every reset: take it with a pair, hand it back to `record`."""
        return self._generation

    @property
    def last_result(self) -> np.ndarray | None:
        """The last recorded result, T_target_source (None after a reset)."""
        return self._last_T

    @property
    def guess(self) -> TopicGuess | None:
        """The topic guess in force (None: none, or discarded)."""
        return self._guess

    def set_guess(self, T: np.ndarray, parent: str, child: str | None, origin: str, now: float) -> None:
        """A guess arrived on topic `origin`: it replaces any earlier one."""
        with self._lock:
            self._guess = TopicGuess(T, parent, child, now, origin)

    def predicted(self, stamp: int) -> np.ndarray | None:
        """The last result moved on to source stamp `stamp` (ns) at the velocity of the last two results
        (`geometry.extrapolate`, at most `MAX_EXTRAPOLATION` of their interval); None when there is no
        earlier result to take a velocity from or the stamps do not increase."""
        with self._lock:
            last_T, last_stamp, previous = self._last_T, self._last_stamp, self._previous
        if last_T is None or previous is None or not previous[1] < last_stamp < stamp:
            return None
        ratio = min((stamp - last_stamp) / (last_stamp - previous[1]), MAX_EXTRAPOLATION)
        return extrapolate(previous[0], last_T, ratio)

    def start(self, config: NodeConfig, source_frame: str, target_frame: str, now: float, *,
              tracking: bool | None = None, parameter: bool = True, stamp: int | None = None,
              predict: bool = True) -> Start:
        """The start of a pair mapping `source_frame` into `target_frame` under `config`
        (initial_guess_timeout, use_last_result_as_guess, initial_guess). `tracking` overrides
        use_last_result_as_guess; `parameter` False leaves the initial_guess parameter out (map mode);
        `stamp`: the pair's source stamp (ns), to move the last result to it by the odometry's motion (`odometry`)
        or, with `predict`, on at the last two results' velocity (`predicted`); None: as kept. Without odometry,
        the first pair after a pose placed by a search (`record`'s `placed`: no velocity) is placed again,
        without a guess."""
        with self._lock:
            g, last_T, last_time, last_stamp = self._guess, self._last_T, self._last_time, self._last_stamp
        discarded = note = ""
        tracking = config.use_last_result_as_guess if tracking is None else tracking
        if g is not None and config.initial_guess_timeout > 0 and now - g.received > config.initial_guess_timeout:
            discarded = "expired"
            note = (f"{g.origin} guess expired ({now - g.received:.1f} s > initial_guess_timeout "
                    f"{config.initial_guess_timeout} s)")
        elif g is not None and (g.parent != target_frame or g.child not in (None, source_frame)):
            discarded = "initial_guess_frames"
            note = (f"{g.origin} guess ignored: it maps {g.child or '(any)'} into '{g.parent}', the pair maps "
                    f"'{source_frame}' into '{target_frame}'")
        elif g is not None and not (tracking and last_time > g.received):
            return Start(g.T, g.origin)
        if discarded:
            with self._lock:
                if self._guess is g:  # not replaced meanwhile
                    self._guess = None
        moved = None if not (tracking and last_T is not None and stamp is not None) else \
            self.odometry.motion(last_stamp, stamp, source_frame)
        if moved is not None:
            return Start(last_T @ moved, "odometry", discarded, note)
        if tracking and last_T is not None and stamp is not None and predict and self._place_again():
            return Start(None, "none", discarded, note)
        if tracking and last_T is not None:
            ahead = None if stamp is None or not predict else self.predicted(stamp)
            if ahead is not None:
                return Start(ahead, "predicted", discarded, note)
            return Start(last_T, "last_result", discarded, note)
        T = config.initial_guess_matrix() if parameter else None
        return Start(T, "none" if T is None else "parameter", discarded, note)

    def _place_again(self) -> bool:
        """Whether the last result was placed by a search (no velocity yet) and no pair has been started to
        place it again since; if so, this pair is that one."""
        with self._lock:
            again = self._placed and not self._again
            self._again = self._again or again
            return again

    def record(self, T: np.ndarray, source_stamp: int, generation: int, now: float, continues: bool = True,
               placed: bool = False) -> bool:
        """Keep a published result for tracking, unless a reset came after its pair was taken (`generation`
        is not the current one) or a newer pair's result is already kept. `continues`: the pair started
        from the last result (origin in `TRACKED`), so the motion from it is the velocity `predicted` goes on
        with (a pose found without it, or from a topic guess, starts afresh). `placed`: the pose was placed by a
        search, not tracked from its start (it had none, or left it: a jump); a placement right after one gives
        the velocity. Whether it was kept."""
        with self._lock:
            if generation != self._generation or source_stamp < self._last_stamp:
                return False
            newer = self._last_T is not None and source_stamp > self._last_stamp
            if placed and self._placed and newer:  # placed twice: the motion between the two placements
                self._previous, self._placed = (self._last_T, self._last_stamp), False
            elif not continues:
                self._previous, self._placed = None, placed
            elif newer:
                self._previous, self._placed = (self._last_T, self._last_stamp), False
            self._again = False
            self._last_T, self._last_time, self._last_stamp = T, now, source_stamp
            return True

    def reset(self) -> None:
        """Forget the topic guess and the last result; results of pairs taken before now are not recorded."""
        with self._lock:
            self._guess, self._last_T, self._last_time, self._last_stamp = None, None, -np.inf, -1
            self._previous, self._placed, self._again = None, False, False
            self._generation += 1
