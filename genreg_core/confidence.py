"""The confidence calibration: the verification features of a pose and the fitted models that turn them
into the probability that it is right.

A registration is verified by how the aligned source sits on the target (`score.overlap_shares`: the
share of source points within 1, 2, 3 and 5 target spacings), how many of the network's generated
correspondences the pose keeps (the inlier ratio) and how well the geometry constrains it
(`score.unconstrained_directions`). A logistic model over those `FEATURES` turns them into P(success),
where success is the model's rule (`ConfidenceModel.success`: scenes RE < 2 deg and TE < 5 cm; objects
RE < 5 deg). It is fitted on training pairs only (`scripts/calibrate_confidence.py`) for one checkpoint,
one model per refinement (a `refinement.REFINEMENTS` name: the features' scale depends on it) and one for
map tracking (`result.TRACKING_CALIBRATION`), one of global results in a map over `MAP_FEATURES`
(`MAP_CALIBRATION`: a registration's probability and how much of the map the pose says the scan saw through), and ships beside the checkpoint as `<name>.confidence.json`,
tied to the checkpoint by its SHA-256: a calibration never silently serves another model, nor a refinement
it was not fitted for. How a result's confidence is worked out from it (the rival, the degeneracy factor,
and a registrar without a calibration for its refinement) is `genreg_core.result`'s.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from genreg_core.errors import CheckpointError

SPACINGS = (1.0, 2.0, 3.0, 5.0)  # overlap shares at these many target spacings
FEATURES = ("log_share_1", "log_share_2", "log_share_3", "log_share_5", "log_inlier_ratio", "log_constraint",
            "share_1_over_3", "share_2_over_5")
FLOOR = 1e-3  # logs of shares below this are taken at it
# see-through shares below this are taken at it: about the lower quartile of right poses' on training maps,
# where a share is noise (few map points in view), not evidence (MODEL_CARD "Map relocalisation: the
# see-through floor")
SEE_THROUGH_FLOOR = 0.01
MAP_CALIBRATION = "map_global"  # the key of the model of global results in a map (`MapLocalizer`): it refines a
MAP_FEATURES = ("logit_probability", "log_see_through")  # registration's probability with the see-through share
FEATURES_OF = {MAP_CALIBRATION: MAP_FEATURES}  # the models over other features than FEATURES
SUFFIX = ".confidence.json"


def features(shares: Sequence[float], inlier_ratio: float, constraint: float) -> np.ndarray:
    """The `FEATURES` vector of one verified pose: overlap `shares` at `SPACINGS`, the generated
    correspondences' inlier ratio, the degeneracy factor (1: fully constrained)."""
    s1, s2, s3, s5 = (max(float(x), FLOOR) for x in shares)
    logs = [math.log(x) for x in (s1, s2, s3, s5, max(inlier_ratio, FLOOR), max(constraint, FLOOR))]
    return np.array([*logs, s1 / s3, s2 / s5])


def map_features(probability: float, see_through: float) -> np.ndarray:
    """The `MAP_FEATURES` vector of a global result in a map: its registration's probability (as a logit, kept
    within FLOOR of 0 and 1) and the log of the share of the map its pose says the scan saw through
    (`score.see_through`, taken at SEE_THROUGH_FLOOR when below)."""
    p = min(max(float(probability), FLOOR), 1.0 - FLOOR)
    return np.array([math.log(p / (1.0 - p)), math.log(max(float(see_through), SEE_THROUGH_FLOOR))])


def feature_vector(verification: dict[str, float]) -> np.ndarray:
    """The `FEATURES` vector of a result's `verification` (`RegistrationResult.verification`)."""
    return np.array([verification[f] for f in FEATURES])


@dataclass(frozen=True)
class Logistic:
    """P(success | features) = 1 / (1 + exp(-(coef . x + intercept)))."""

    coef: tuple[float, ...]  # one per FEATURES entry
    intercept: float

    def probability(self, x: np.ndarray) -> float:
        z = float(np.dot(self.coef, x)) + self.intercept
        return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0


@dataclass(frozen=True)
class ConfidenceModel:
    """A checkpoint's calibration: one fitted `Logistic` per refinement it serves (the features' scale depends
    on how the pose was refined), and what it was fitted for."""

    by_refinement: dict[str, Logistic]  # RefineConfig.method (or result.TRACKING_CALIBRATION) -> its model
    success: str  # the success rule the probability is of, e.g. "RE < 2 deg and TE < 0.05 m"
    checkpoint_sha256: str  # the checkpoint it belongs to
    fitted_on: str  # the training pairs
    date: str
    features: tuple[str, ...] = FEATURES

    def serves(self, refine_method: str) -> bool:
        """Whether it was fitted for results refined this way."""
        return refine_method in self.by_refinement

    def probability(self, x: np.ndarray, refine_method: str) -> float:
        """P(success) of one `features` vector of a result refined by `refine_method` (one it serves)."""
        return self.by_refinement[refine_method].probability(x)

    def save(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        path.write_text(json.dumps(asdict(self), indent=1) + "\n")
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, checkpoint: str | os.PathLike | None = None) -> ConfidenceModel:
        """Read a calibration; with `checkpoint`, check that it was fitted for that file (CheckpointError)."""
        try:
            values = json.loads(Path(path).read_text())
            models = {k: Logistic(tuple(v["coef"]), float(v["intercept"])) for k, v in values["by_refinement"].items()}
            model = cls(**{**values, "by_refinement": models, "features": tuple(values["features"])})
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
            raise CheckpointError(f"confidence calibration {path} is unreadable: {exc}") from None
        if model.features != FEATURES or any(len(m.coef) != len(FEATURES_OF.get(k, FEATURES)) for k, m in models.items()):
            raise CheckpointError(f"confidence calibration {path} has features {model.features}, expected {FEATURES}")
        if checkpoint is not None and model.checkpoint_sha256 != file_sha256(checkpoint):
            raise CheckpointError(f"confidence calibration {path} was fitted for another checkpoint than {checkpoint}")
        return model


def file_sha256(path: str | os.PathLike) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def calibration_path(checkpoint: str | os.PathLike) -> Path:
    """Where a checkpoint's calibration lives: beside it, `<stem>.confidence.json`."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.stem + SUFFIX)


def load_beside(checkpoint: str | os.PathLike) -> ConfidenceModel | None:
    """The calibration beside a checkpoint file, or None if it has none."""
    path = calibration_path(checkpoint)
    return ConfidenceModel.load(path, checkpoint) if path.is_file() else None
