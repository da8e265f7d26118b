"""Pipeline stage "verify": how well a candidate pose of one prepared pair explains the clouds.

Every score of a pair is taken in the pair's normalised frame against its one target index
(`PreparedPair.target_index`): the overlap shares (`score.overlap_fitness`, `score.overlap_shares`), the
agreement of the network's generated correspondences with the pose (their inlier ratio), and the
calibrated probability that the pose is right (`genreg_core.confidence`), which chooses among PDSAC's
modes. Frames and units: `genreg_core.geometry`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from genreg_core.confidence import SPACINGS, ConfidenceModel, features
from genreg_core.prepare import PreparedPair
from genreg_core.score import TIGHT_SPACINGS, fitness_distance, overlap_fitness, overlap_shares


@dataclass
class Verifier:
    """The scores of candidate poses T (normalised frame, b ~ T a) of one pair: `pair`, the network's
    generated clouds for it (A_g, B_g: (N, 3) tensors), PDSAC's inlier threshold `tau` in that frame, and
    the calibration serving the pair's refinement (None: no calibrated probability)."""

    pair: PreparedPair
    source_generated: torch.Tensor
    target_generated: torch.Tensor
    tau: float
    calibration: ConfidenceModel | None = None
    refine_method: str = "none"
    separation: float = 15.0  # deg: two poses this far apart in rotation are distinct (`pdsac.mode_separation`)

    @property
    def distance(self) -> float:
        """The fitness radius: `score.FITNESS_SPACINGS` target spacings."""
        return fitness_distance(self.pair.target_index)

    def fitness(self, T: np.ndarray) -> tuple[float, float]:
        """(share of the source within the fitness radius, their RMS distance)."""
        return overlap_fitness(self.pair.dense_src, self.pair.target_index, T, self.distance)

    def tight(self, T: np.ndarray) -> float:
        """The share of the source within one target spacing."""
        p = self.pair
        return overlap_fitness(p.dense_src, p.target_index, T, TIGHT_SPACINGS * p.target_index.spacing)[0]

    def closer(self, T_a: np.ndarray, T_b: np.ndarray, margin: float = 0.0) -> bool:
        """Whether T_a puts a larger share (by more than `margin`) of the source within one spacing (not
        three: there a wrong pose that pushes a partial source's unmatched part onto the target can
        overlap more than the true one; MODEL_CARD "guard")."""
        return self.tight(T_a) > self.tight(T_b) + margin

    def shares(self, T: np.ndarray) -> np.ndarray:
        """The shares of the source within each of `confidence.SPACINGS` target spacings."""
        p = self.pair
        return overlap_shares(p.dense_src, p.target_index, T, np.multiply(SPACINGS, p.target_index.spacing))

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

    def probability(self, T: np.ndarray, inlier_ratio: float | None = None, constraint: float = 1.0) -> float:
        """The calibrated probability that T is right (a calibration is needed), from its shares, the
        inlier ratio (default: `agreement`) and the degeneracy factor."""
        ratio = self.agreement(T) if inlier_ratio is None else inlier_ratio
        return self.calibration.probability(features(self.shares(T), ratio, constraint), self.refine_method)
