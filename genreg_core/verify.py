"""Pipeline stage "verify": how well a candidate pose of one prepared pair explains the clouds.

Every score of a pair is taken in the pair's normalised frame against its one target index
(`PreparedPair.target_index`): the overlap shares (the share of the source within 1, 2, 3 and 5 target
spacings; fitness is the share within `score.FITNESS_SPACINGS`, tight fitness within one), the agreement of
the network's generated correspondences with the pose (their inlier ratio), the overlap score the guard and
the fallback test, and the calibrated probability that the pose is right (`result.Confidence`), which
chooses among the candidates. `verify` and `aligned` hand the chosen pose to `result.build_result`. Each pose
is looked up in the target index once: every score of it is read from that one query. One score is taken in
input units instead: `seen_through` casts the source's rays from its sensor, the origin of the input's frame (the
normalisation moves it), over the target's points in metres. Frames and units: `genreg_core.geometry`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import torch

from genreg_core.confidence import SPACINGS, features
from genreg_core.geometry import apply_transform, moved_along, rotation_angle, turned_about
from genreg_core.prepare import PreparedPair
from genreg_core.result import Aligned, Confidence, Verified
from genreg_core.score import FITNESS_SPACINGS, TIGHT_SPACINGS, overlap_score, see_through

REMEMBERED_POSES = 8  # a Verifier keeps the squared distances of this many poses (a pair's candidates)
SLIDE_SPACINGS = 4  # `Verifier.slid` moves a pose this many target spacings along the source's main axis (MODEL_CARD
# "LiDAR pairs metres apart": 2 held a third of the training campuses' right consecutive drive scans)
SLIDE_SEAT_SPACINGS = 2.0  # ... and counts the source points within this many target spacings, at the pose and slid
# (MODEL_CARD "LiDAR pairs: slides counted within two spacings": within one, a corridor's scans can fit best with the
# two sensors put together, where their rings coincide, the pose slid towards the right one seating 15-60 % fewer)
TURNS_DEG = (90.0, 180.0, 270.0)  # `Verifier.turned` turns a pose by these angles about the source's up axis
TURN_START_SHARE = 0.2  # ... and aligns a turn again only where, as it is, it seats this share of the points the pose
# seats that not every turn seats (the ground about the sensor seats whatever the turn; MODEL_CARD "LiDAR pairs: turned
# rivals": on the training campuses every turn that aligned to 0.85 or more seated 0.23 or more of all the pose's
# points; counting only those a turn changes, consecutive drive scans align a third fewer turns, the same poses held)
THROUGH_SPACING = 0.5  # m: `Verifier.seen_through` counts a target point as in front of the source's return along its
# ray when nearer by `score.SEE_THROUGH_SPACINGS` times this (and 2 % of the range): the LiDAR profile's voxel, so that
# voxelised surfaces are not mistaken for seen-through ones (MODEL_CARD "LiDAR pairs: seen through")
THROUGH_HEIGHT = 1.0  # m: ... over the target's structure, its points this high or more above the source's ground (the
# ground about a sensor is seen between its rings: counted, right street poses saw through up to 0.16 of it)
THROUGH_GROUND_QUANTILE = 0.1  # ... the source's ground: this quantile of its points' heights


@dataclass
class Verifier:
    """The scores of candidate poses T (normalised frame, b ~ T a) of one pair: `pair`, the network's
    generated clouds for it (A_g, B_g: (N, 3) tensors), PDSAC's inlier threshold `tau` in that frame, and
    how the confidence of the pair's refinement is worked out (`probability` needs it calibrated)."""

    pair: PreparedPair
    source_generated: torch.Tensor
    target_generated: torch.Tensor
    tau: float
    confidence: Confidence
    separation: float = 15.0  # deg: two poses this far apart in rotation are distinct (`pdsac.mode_separation`)
    _squared: dict[bytes, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def distance(self) -> float:
        """The fitness radius: `score.FITNESS_SPACINGS` target spacings."""
        return FITNESS_SPACINGS * self.pair.target_index.spacing

    def squared(self, T: np.ndarray) -> np.ndarray:
        """Squared distance from each refinement-size source point moved by T to its nearest target point:
        one query of the target index per pose (the last `REMEMBERED_POSES` poses are kept)."""
        key = np.ascontiguousarray(T, dtype=np.float64).tobytes()
        found = self._squared.get(key)
        if found is None:
            _, found = self.pair.target_index.nearest(apply_transform(T, self.pair.dense_src.astype(np.float64)))
            if len(self._squared) >= REMEMBERED_POSES:
                self._squared.pop(next(iter(self._squared)))
            self._squared[key] = found
        return found

    def fitness(self, T: np.ndarray) -> tuple[float, float]:
        """(share of the source within the fitness radius, their RMS distance; 0 when none is within)."""
        squared = self.squared(T)
        inliers = squared[squared < self.distance ** 2]
        return len(inliers) / len(squared), float(np.sqrt(inliers.mean())) if len(inliers) else 0.0

    def seats(self, T: np.ndarray, spacings: float = TIGHT_SPACINGS) -> np.ndarray:
        """Which refinement-size source points T puts within this many target spacings (default one; bool)."""
        return self.squared(T) < (spacings * self.pair.target_index.spacing) ** 2

    def within(self, T: np.ndarray, spacings: float) -> float:
        """The share of the source within this many target spacings."""
        return float(np.mean(self.seats(T, spacings)))

    def tight(self, T: np.ndarray) -> float:
        """The share of the source within one target spacing."""
        return self.within(T, TIGHT_SPACINGS)

    def closer(self, T_a: np.ndarray, T_b: np.ndarray, margin: float = 0.0) -> bool:
        """Whether T_a puts a larger share (by more than `margin`) of the source within one spacing (not
        three: there a wrong pose that pushes a partial source's unmatched part onto the target can
        overlap more than the true one; MODEL_CARD "guard")."""
        return self.tight(T_a) > self.tight(T_b) + margin

    def slid(self, T: np.ndarray) -> tuple[np.ndarray, float]:
        """(the main axis of the source moved by T: the unit principal axis of its points, a road's or a corridor's
        direction; the larger share of the source within `SLIDE_SEAT_SPACINGS` target spacings at T moved
        `SLIDE_SPACINGS` spacings along it either way, over T's own): about 1 or more where the target is alike along
        the axis, so the fit does not tell where along it the source lies; 0 when T seats no point."""
        moved = apply_transform(T, self.pair.dense_src.astype(np.float64))
        centred = moved - moved.mean(axis=0)
        axis = np.linalg.eigh(centred.T @ centred)[1][:, -1]
        own, shift = self.within(T, SLIDE_SEAT_SPACINGS), SLIDE_SPACINGS * self.pair.target_index.spacing
        slid = max(self.within(S, SLIDE_SEAT_SPACINGS) for S in moved_along(T, axis, (shift, -shift)))
        return axis, slid / own if own > 0 else 0.0

    def turned(self, T: np.ndarray, up: np.ndarray, sensor: np.ndarray, align: Callable[[np.ndarray], np.ndarray]
               ) -> tuple[np.ndarray, float]:
        """(the best turned rival of T, its share of the source within one target spacing over T's own `tight`):
        T turned by each of `TURNS_DEG` about the unit `up` axis (the source's z in the target frame) through the
        `sensor` (the source frame's origin moved by T), each aligned again by `align` (refinement from a start)
        where, as it is, it seats `TURN_START_SHARE` of the source points T seats within one spacing that not every
        turn seats (the ground about the sensor seats whatever the turn); only rivals more than `separation` deg from T
        count (a turn that aligns back onto T is no rival). About 1 or more where the target looks alike turned
        around (a corridor, a square hall), so the fit does not tell which way the source faces; (T, 0) when none
        is distinct or T seats no point."""
        own, best, share = self.tight(T), T, 0.0
        if own <= 0:
            return best, share
        starts = turned_about(T, up, sensor, np.radians(TURNS_DEG))
        seated = [self.seats(S) for S in (T, *starts)]
        varying = ~np.logical_and.reduce(seated)  # what every turn seats alike (the ground about the sensor) tells none
        own_varying = np.count_nonzero(seated[0] & varying)
        for start, at_start in zip(starts, seated[1:], strict=True):
            if np.count_nonzero(at_start & varying) < TURN_START_SHARE * own_varying:
                continue
            rival = align(start)
            fit = self.tight(rival) / own
            if fit > share and np.degrees(rotation_angle(rival[:3, :3] @ T[:3, :3].T)) > self.separation:
                best, share = rival, fit
        return best, share

    def seen_through(self, T: np.ndarray) -> float:
        """The share of the target's structure that the source, placed by the input-units pose T, would have seen
        through (`score.see_through`: the source's returns, its frame the sensor's, over the refinement-size target points
        `THROUGH_HEIGHT` m or more above the source's ground, the `THROUGH_GROUND_QUANTILE` quantile of its heights; z up,
        a level LiDAR; metres): a pose turned or slid along a corridor puts walls where the source saw through doorways
        and down other corridors. 0 when no target point stands that high."""
        p = self.pair
        source = np.asarray(p.src, dtype=np.float64)
        target = p.points_to_input_units(p.dense_tgt.astype(np.float64))
        height = ((target - T[:3, 3]) @ T[:3, :3])[:, 2]  # in the source's frame
        structure = target[height >= np.quantile(source[:, 2], THROUGH_GROUND_QUANTILE) + THROUGH_HEIGHT]
        return see_through(source, structure, T, THROUGH_SPACING)[0] if len(structure) else 0.0

    def shares(self, T: np.ndarray) -> np.ndarray:
        """The shares of the source within each of `confidence.SPACINGS` target spacings."""
        limits = np.square(np.multiply(SPACINGS, self.pair.target_index.spacing))
        return (self.squared(T)[None, :] < limits[:, None]).mean(axis=1)

    @cached_property
    def correspondences(self) -> tuple[np.ndarray, np.ndarray]:
        """The union of the generated correspondences, {A_i -> A_g,i} and {B_g,i -> B_i}, as float64 arrays
        (source side, target side) (`pdsac.union_correspondences`)."""
        p = self.pair
        src = np.concatenate([p.a, self.target_generated.double().cpu().numpy()])
        dst = np.concatenate([self.source_generated.double().cpu().numpy(), p.b])
        return src.astype(np.float64), dst

    def agreement(self, T: np.ndarray) -> float:
        """The inlier ratio of the generated correspondences (both directions) under T (`pdsac.union_inlier_share`,
        in numpy: no torch thread pool for 1,024 rows)."""
        src, dst = self.correspondences
        residual = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1)
        return float(np.mean(residual < self.tau))

    def overlap_score(self, T: np.ndarray, inlier_ratio: float) -> float:
        """T's overlap score (`score.overlap_score`) with this inlier ratio: what the guard and the fallback test."""
        return overlap_score(self.fitness(T)[0], self.tight(T), inlier_ratio)

    def probability(self, T: np.ndarray) -> float:
        """The calibrated probability that T is right as a candidate (`Confidence.probability` of its features
        with its `agreement`, the geometry taken as constrained; a calibrated `confidence` is needed)."""
        return self.confidence.probability(features(self.shares(T), self.agreement(T), 1.0))

    def verify(self, T: np.ndarray, inlier_ratio: float, rival: float = 0.0) -> Verified:
        """The chosen pose T verified, for its result (`result.build_result`): its shares, fitness, tight
        fitness and their RMS distance (normalised frame), with its inlier ratio and its rival's probability."""
        fitness, rmse = self.fitness(T)
        return Verified(self.shares(T), fitness, self.tight(T), rmse, inlier_ratio, rival)

    def aligned(self, T: np.ndarray, origin: np.ndarray) -> Aligned:
        """The pair's refinement-size source moved by T onto the target index (normalised frame; `origin`: the
        pose's position there), for the covariance and the degeneracy (`result.build_result`)."""
        return Aligned(apply_transform(T, self.pair.dense_src.astype(np.float64)), self.pair.target_index, origin,
                       self.distance, self.pair.scale)
