"""register_node's latency budget: a pair that would be late is registered with less work.

A pair's latency runs from the arrival of its later cloud to its result. When the node falls behind, a pair
waits for a free worker first. `LatencyBudget.plan` looks at the pair's age when a worker takes it: if that
age plus the expected seconds of a full registration exceed `budget.latency`, the pair is registered with the
light settings (`light_config`: no PDSAC modes, no further network passes, no guard ICP, no tight refinement
stage, at most `budget.light_points` refinement points). A pair already older than the budget goes light.
The expected seconds are the `QUANTILE` of the last `WINDOW` full registrations (none yet: full), so that a
pair that goes full finishes within the budget nine times in ten, not only on average; while pairs go
light, a pair that is not late yet still goes full every `PROBE_S` seconds, so the expectation keeps up
with the load. A light pair is counted (`light` in /diagnostics) and says so in
its registration_status (`budget: light`). Pure Python, thread-safe.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import replace

from genreg_core.config import RegistrationConfig

WINDOW = 20  # the recent full registrations whose seconds the expectation reads
QUANTILE = 0.9  # the expectation: this quantile of their seconds
PROBE_S = 10.0  # while pairs go light, one that is not late yet is registered in full this often, s: the
# expectation follows the load back down


def light_config(config: RegistrationConfig, refine_points: int) -> RegistrationConfig:
    """`config` with the work a confident first answer does not need switched off: one network pass, no
    search of PDSAC's other modes, no guard ICP from identity, one refinement stage, at most `refine_points`
    refinement (and verification) points."""
    return replace(config, passes=1, pdsac=replace(config.pdsac, modes_below=0.0),
                   refine=replace(config.refine, guard_below=0.0, fine_fraction=1.0,
                                  num_points=min(config.refine.num_points, refine_points)))


class LatencyBudget:
    """Chooses full or light registration per pair so that its latency stays within a budget, learning how
    long a full registration takes from the pairs registered in full."""

    def __init__(self) -> None:
        self._full: deque[float] = deque(maxlen=WINDOW)  # the recent full registrations' seconds
        self._last_full = -1e9  # time.monotonic() of the last full registration's start
        self._light: tuple[RegistrationConfig, int, RegistrationConfig] | None = None  # (full, points, light)
        self._lock = threading.Lock()

    @property
    def expected_full(self) -> float | None:
        """The `QUANTILE` of the recent full registrations' seconds (None before the first)."""
        with self._lock:
            return self._expected()

    def _expected(self) -> float | None:
        if not self._full:
            return None
        ordered = sorted(self._full)
        return ordered[min(len(ordered) - 1, int(QUANTILE * len(ordered)))]

    def plan(self, age: float, config: RegistrationConfig, budget: float, light_points: int
             ) -> tuple[bool, RegistrationConfig]:
        """(light, the settings to register with) for a pair `age` seconds after its later cloud arrived, under
        a budget of `budget` seconds (0: off) with `light_points` refinement points when light. The settings
        are `config` itself when full, and one light object per `config` object and `light_points`, so a
        registrar's settings change (and travel to a worker) only when full and light alternate."""
        now = time.monotonic()
        with self._lock:
            expected = self._expected()
            late = budget > 0 and (age >= budget or (expected is not None and age + expected > budget
                                                     and now - self._last_full < PROBE_S))
            if not late:
                self._last_full = now
                return False, config
            cached = self._light
            if cached is None or cached[0] is not config or cached[1] != light_points:
                cached = self._light = (config, light_points, light_config(config, light_points))
            return True, cached[2]

    def record(self, light: bool, seconds: float) -> None:
        """A registration's seconds (only full ones teach the expectation)."""
        if light:
            return
        with self._lock:
            self._full.append(seconds)
