"""Pipeline stage "result": the confidence of a verified pose and the `RegistrationResult` that reports it.

The one home of the confidence. A pose is verified (by `verify.Verifier` in the registration pipeline,
by `MapLocalizer.track` in map tracking) into a `Verified`: its overlap shares at `confidence.SPACINGS`
target spacings, its fitness and tight fitness, the inlier ratio of the network's generated
correspondences under it and the probability of its rival (the best other, distinct pose: two distinct
poses cannot both be right). `build_result` adds how well the geometry constrains the pose (the
covariance, the unconstrained motions and the degeneracy factor, `score.unconstrained_directions`) and
turns it into the one final result of registration and map localisation alike: the confidence
(`Confidence.of`), the verification features (`confidence.FEATURES`), scores and clouds in the input's
units.

The confidence is the probability that the pose is right (the model's success rule), from the checkpoint's
calibration (`confidence.ConfidenceModel`): its model for how the pose was found (`Confidence.key`: the
refinement method, `refinement.REFINEMENTS`, or `TRACKING_CALIBRATION` for map tracking) over the
verification features, at most 1 - the rival's probability, times the degeneracy factor.

A pose that the geometry leaves free to slide along an axis (a road, a corridor: `MapLocalizer.flat` in map
tracking, `Registrar.slide_checked` in registration) is named by `as_well_fitted` ("translation along (x, y, z): as
well fitted d m along it") and its covariance widened along the axis (`spanning`); a pose bounded by a distinct rival
pose is named and widened towards it by `rivalled`, one whose source seats as well turned about its up axis (a corridor
alike turned around: `Registrar.turn_checked`) by `as_well_turned`. Whether a named pose's confidence is held is its
caller's rule.

Uncalibrated (one behaviour, documented here): a checkpoint without a calibration, or whose calibration
has no model for the refinement in use, gets the overlap score instead (`score.overlap_score`: the
geometric mean of fitness, tight fitness and inlier ratio; 1 for a pose without generated
correspondences), times the degeneracy factor. It is not a probability, and what needs one is off: PDSAC's
other modes and more network passes. The `Registrar` says so with an `errors.UncalibratedWarning` when it is
built or its refinement changes; it does not refuse: the node's default refinement (point-to-point) with
the scene checkpoint and the benchmarks' refinement rows run such combinations on purpose. Map tracking
runs only with the calibration's tracking model (`MapLocalizer.tracking_calibrated`); `MapLocalizer.track`
called without it scores the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from genreg_core.confidence import FEATURES, ConfidenceModel, features
from genreg_core.geometry import rotation_angle
from genreg_core.score import (
    COVARIANCE_FLOOR_M,
    COVARIANCE_FLOOR_RAD,
    COVARIANCE_INFLATION,
    TargetIndex,
    motion,
    overlap_score,
    pose_covariance,
    unconstrained_directions,
)

AS_WELL_FITTED = "as well fitted"  # the name of a flat axis among a result's unconstrained motions (`as_well_fitted`)
# The shares stage 9's checks leave in a result's `verification` when they ran (`Registrar.slide_checked`,
# `turn_checked`, `through_checked`): the slid, the turned rival's and the seen-through share
SLIDE_SHARE, TURN_SHARE, THROUGH_SHARE = "slide_share", "turn_share", "through_share"
CHECK_SHARES = (SLIDE_SHARE, TURN_SHARE, THROUGH_SHARE)
TRACKING_CALIBRATION = "map_tracking"  # the calibration's key of map tracking's model (`ConfidenceModel.by_refinement`)
# What a final pose grew from (`RegistrationResult.start`): GenReg's estimate (or another PDSAC mode, or another
# pass), the given initial guess, the guard's refinement from identity (no guess given), the classical fallback.
STARTS = ("genreg", "initial_guess", "guard", "fallback")


@dataclass
class RegistrationResult:
    """Result of one registration. Transform and clouds are in the input's units."""

    transformation: np.ndarray  # (4, 4) float64, target_from_source
    source_generated: np.ndarray  # A_g: (n, 3) model-resolution source generated in the target frame
    target_generated: np.ndarray  # B_g: (n, 3) model-resolution target generated in the source frame
    aligned_source: np.ndarray  # (K, 3) float32: the finite source points, input order, in target frame
    source_valid_mask: np.ndarray  # (N,) bool: which input source rows were finite (and kept)
    fitness: float  # share of sampled source points with a target point within 3x the target's spacing
    tight_fitness: float  # the same share within 1x the target's spacing
    inlier_ratio: float  # fraction of generated correspondences (both directions) consistent with T; NaN for a pose
    # aligned without the network (map tracking and the place index's poses: `MapLocalizer.verified`)
    inlier_rmse: float  # RMS distance of the fitness inliers, input units
    confidence: float  # the probability that the pose is right (the model's success rule), uncalibrated the
    # overlap score; times the degeneracy factor (`genreg_core.result`, `Confidence.of`)
    start: str = "genreg"  # what the final pose grew from (`STARTS`): "genreg", "initial_guess" (the given
    # guess, refined or kept), "guard" (the guard's refinement from identity, no guess given) or "fallback"
    covariance: np.ndarray | None = None  # (6, 6) of the final pose, ROS order (x, y, z, rot x, y, z), m, rad
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage (`STAGES`; those that ran) and
    # 'total'; with more passes, the first pass's stages, 'passes' the other passes' seconds, 'total' of all
    passes: int = 1  # network passes run (`RegistrationConfig.passes`: more only while unsure)
    unconstrained: tuple[str, ...] = ()  # motions the aligned geometry does not constrain, target frame, e.g.
    # "rotation about (0.00, 0.00, 1.00)" (score.unconstrained_directions); empty: fully constrained

    verification: dict[str, float] = field(default_factory=dict)  # the confidence's inputs (confidence.FEATURES)

    @property
    def degenerate(self) -> bool:
        """Whether the geometry leaves some motion unconstrained (`unconstrained` is not empty)."""
        return bool(self.unconstrained)


@dataclass(frozen=True)
class Verified:
    """A pose as verification found it: how its source sits on the target (lengths in the frame it was
    verified in) and what else bounds its confidence."""

    shares: np.ndarray  # the share of the source within each of `confidence.SPACINGS` target spacings
    fitness: float  # the share within `score.FITNESS_SPACINGS` spacings
    tight_fitness: float  # the share within `score.TIGHT_SPACINGS`
    rmse: float  # RMS distance of the fitness inliers
    inlier_ratio: float  # of the generated correspondences under the pose; NaN: none (map tracking)
    rival: float = 0.0  # the probability that another, distinct pose is right

    @property
    def agreement(self) -> float:
        """The inlier ratio as the confidence takes it: 1 for a pose without generated correspondences."""
        return 1.0 if math.isnan(self.inlier_ratio) else self.inlier_ratio

    def features(self, constraint: float) -> np.ndarray:
        """The calibration's `confidence.FEATURES` of the pose at this degeneracy factor."""
        return features(self.shares, self.agreement, constraint)


@dataclass(frozen=True)
class Aligned:
    """A pose's source points on its target, in one frame: what the covariance and the degeneracy are
    worked out on."""

    moved: np.ndarray  # (n, 3) float64: the source points moved by the pose
    index: TargetIndex  # the target
    origin: np.ndarray  # (3,): the pose's position (the covariance's rotations are about it)
    distance: float  # the fitness radius: correspondences within it count
    scale: float = 1.0  # this frame's lengths times `scale` are the input's units (metres)


def below_rival(probability: float, rival: float) -> float:
    """A pose's probability bounded by its rival's: two distinct poses cannot both be right."""
    return min(probability, 1.0 - rival)


@dataclass(frozen=True)
class Confidence:
    """How the confidence of poses found one way is worked out: `key` names the way (a refinement method or
    `TRACKING_CALIBRATION`), `calibration` is the checkpoint's (None: it has none, or it is not to be used)."""

    calibration: ConfidenceModel | None
    key: str

    @property
    def calibrated(self) -> bool:
        """Whether the calibration has a model for `key`: the confidence is then a probability."""
        return self.calibration is not None and self.calibration.serves(self.key)

    def probability(self, x: np.ndarray) -> float:
        """The calibrated probability of one `confidence.features` vector, before the rival and the degeneracy
        factor: what candidates are compared by (calibrated only)."""
        return self.calibration.probability(x, self.key)

    def of(self, verified: Verified, constraint: float) -> float:
        """The confidence of a verified pose whose geometry has this degeneracy factor: the calibrated
        probability bounded by the rival's, else (uncalibrated) the overlap score; times the factor."""
        if not self.calibrated:
            return constraint * overlap_score(verified.fitness, verified.tight_fitness, verified.agreement)
        return constraint * below_rival(self.probability(verified.features(constraint)), verified.rival)


def build_result(transformation: np.ndarray, verified: Verified, aligned: Aligned, confidence: Confidence, *,
                 start: str, aligned_source: np.ndarray, source_valid_mask: np.ndarray,
                 source_generated: np.ndarray | None = None, target_generated: np.ndarray | None = None
                 ) -> RegistrationResult:
    """The final result of a verified pose (`transformation`: input units; `verified` and `aligned`: in the
    frame it was verified in, `aligned.scale` to input units): its covariance (metric, `score.pose_covariance`
    with the calibrated model error), unconstrained motions and degeneracy factor, confidence and
    verification features. Without generated clouds (map tracking) they are empty, (0, 3). `timings` are the
    caller's to fill in."""
    covariance = pose_covariance(aligned.moved, aligned.index, aligned.origin, aligned.distance, COVARIANCE_INFLATION,
                                 (COVARIANCE_FLOOR_M, COVARIANCE_FLOOR_RAD), scale=aligned.scale)
    unconstrained, constraint = unconstrained_directions(aligned.moved, aligned.index, aligned.distance)
    return RegistrationResult(
        transformation=transformation,
        source_generated=np.zeros((0, 3), np.float32) if source_generated is None else source_generated,
        target_generated=np.zeros((0, 3), np.float32) if target_generated is None else target_generated,
        aligned_source=aligned_source,
        source_valid_mask=source_valid_mask,
        fitness=verified.fitness,
        tight_fitness=verified.tight_fitness,
        inlier_ratio=verified.inlier_ratio,
        inlier_rmse=verified.rmse * aligned.scale,
        confidence=confidence.of(verified, constraint),
        start=start,
        covariance=covariance,
        unconstrained=unconstrained,
        verification=dict(zip(FEATURES, verified.features(constraint).tolist(), strict=True)),
    )


def spanning(result: RegistrationResult, offset: np.ndarray, weight: float, text: str) -> RegistrationResult:
    """`result` with `text` among its unconstrained motions and its covariance widened along a translation
    `offset` (target frame, input units): `weight` offset offset^T added to the translation block (a mixture of
    two poses `offset` apart, of probabilities p and 1 - p: weight p (1 - p); a flat valley spanning it: 1)."""
    covariance = None if result.covariance is None else result.covariance.copy()
    if covariance is not None:
        covariance[:3, :3] += weight * np.outer(offset, offset)
    return replace(result, covariance=covariance, unconstrained=(*result.unconstrained, text))


def as_well_fitted(result: RegistrationResult, offset: np.ndarray) -> RegistrationResult:
    """`result` whose source seats about as well moved by the translation `offset` (target frame, input units: a
    road's or a corridor's direction, where the fit does not tell where along it the source lies): the axis named
    among its unconstrained motions ("translation along (x, y, z): as well fitted d m along it") and the
    covariance widened by offset offset^T (`spanning`). Its confidence is the caller's to hold."""
    text = f"{motion('translation along', offset)}: {AS_WELL_FITTED} {np.linalg.norm(offset):.2f} m along it"
    return spanning(result, offset, 1.0, text)


def as_well_turned(result: RegistrationResult, rival: np.ndarray, axis: np.ndarray) -> RegistrationResult:
    """`result` whose source seats about as well at the distinct `rival` pose (4x4, input units), turned about the unit
    `axis` (target frame): the turn named among its unconstrained motions ("rotation about (x, y, z): as well fitted
    turned 180 deg, 0.42 m away") and the covariance widened by the rival's offset (`spanning`) and by the turn's
    square about the axis. Its confidence is the caller's to hold."""
    angle = float(np.degrees(rotation_angle(rival[:3, :3] @ result.transformation[:3, :3].T)))
    offset = rival[:3, 3] - result.transformation[:3, 3]
    text = (f"{motion('rotation about', axis)}: {AS_WELL_FITTED} turned {angle:.0f} deg, "
            f"{np.linalg.norm(offset):.2f} m away")
    widened = spanning(result, offset, 1.0, text)
    if widened.covariance is not None:
        widened.covariance[3:, 3:] += np.radians(angle) ** 2 * np.outer(axis, axis)
    return widened


def rivalled(result: RegistrationResult, rival: RegistrationResult, weight: float, p: float) -> RegistrationResult:
    """`result` bounded by a distinct `rival` pose of probability `p`: its confidence at most 1 - p
    (`below_rival`), the rival named among its unconstrained motions ("translation along (x, y, z) to a rival pose
    d m away") and their offset widening its covariance by `weight` (`spanning`)."""
    offset = rival.transformation[:3, 3] - result.transformation[:3, 3]
    slide = f"{motion('translation along', offset)} to a rival pose {np.linalg.norm(offset):.2f} m away"
    return replace(spanning(result, offset, weight, slide), confidence=below_rival(result.confidence, p))
