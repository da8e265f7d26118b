"""The refinement methods: one registry of how the pipeline refines a pose after PDSAC.

Each `Refinement` is one `RefineConfig.method`: the function that refines (`align`, an `Align`), what the
pipeline hands it as the target (`target`, an attribute of `prepare.PreparedPair`: the form of the target
cloud the method is fastest on) and whether a checkpoint's confidence calibration is to serve it
(`calibrated`). Everything that depends on the method reads it from here: `RefineConfig.method`'s choices
are the registry's names, `refine.refine` and `refine.guard_icp` run its function, the pipeline gives it
its target, and a calibration keys its models by its name (`ConfidenceModel.by_refinement`).

Adding a method: its function (e.g. in `genreg_core.refine`), one entry in `REFINEMENTS`, and its model in
each checkpoint's calibration (`scripts/calibrate_confidence.py`). Until a checkpoint's calibration has
that model, the registrar warns when it is built with the method and its confidence is uncalibrated
(`genreg_core.result`).

This module imports no numerical library (`genreg_core.config` reads the names from it, and the node's
parameters come from the config): a method's function is imported when it first runs.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from genreg_core.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np


class Align(Protocol):
    """A refinement: the 4x4 target_from_source it converges to from `init`, in the units of the points;
    `max_iterations` at `max_distance`, then `fine` = (distance, iterations) more if given (the tight
    stage). `target` is the `Refinement.target` the pipeline hands it, or the target as an array."""

    def __call__(self, source: np.ndarray, target: Any, init: np.ndarray, *, max_distance: float,
                 max_iterations: int, fine: tuple[float, int] | None = None) -> np.ndarray: ...


@dataclass(frozen=True)
class Refinement:
    """One refinement method of the registry."""

    name: str  # the `RefineConfig.method` value and the calibration's key
    align: str | None  # "module:function" that refines (an `Align`), imported when first run; None: no refinement
    target: str  # what the pipeline aligns against, a `PreparedPair` attribute: "dense_tgt" (the refinement
    # points), "plane_target" (an Open3D cloud carrying the target's normals), "target_index" (the scores'
    # `TargetIndex`, whose k-d tree and once-prepared covariances GICP uses)
    calibrated: bool = True  # its results are scored by the calibration's model of this name (a checkpoint
    # whose calibration has none gets the uncalibrated confidence, with a warning); False: never calibrated

    @property
    def refines(self) -> bool:
        """Whether it moves the pose ("none" does not)."""
        return self.align is not None

    def function(self) -> Align:
        """The function that refines (a method that refines)."""
        module, name = str(self.align).split(":")
        return getattr(importlib.import_module(module), name)


REFINEMENTS: dict[str, Refinement] = {r.name: r for r in (
    Refinement("none", None, "dense_tgt"),
    Refinement("point_to_point", "genreg_core.refine:point_to_point", "dense_tgt"),
    Refinement("point_to_plane", "genreg_core.refine:point_to_plane", "plane_target"),
    Refinement("gicp", "genreg_core.refine:gicp_on_index", "target_index"),
)}


def refinement(name: str) -> Refinement:
    """The registry's method `name` (ConfigError if there is none)."""
    try:
        return REFINEMENTS[name]
    except KeyError:
        raise ConfigError(f"refine.method must be one of {list(REFINEMENTS)}, got {name!r}") from None
