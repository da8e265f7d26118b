"""The registration pipeline: the algorithm in paper order, one stage per module.

    reg = Registrar.from_checkpoint()              # the object model (config.OBJECT_MODEL); "7scenes": scenes
    result = reg.register(source, target)          # (N, 3) and (M, 3) arrays, any units
    target_points ~ apply_transform(result.transformation, source_points)

Stages of `register_many` (`register` is one pair of it):
    1. prepare    `prepare.prepare_pair`: validate, initial guess, one similarity, distinct subsets of N
    2. encode     `model.encode`: per-point rotation-invariant features of both clouds
    3. interact   `model.interact`: the feature interaction (soft pointer) between the clouds
    4. generate   `model.generate`: A_g (the source in the target frame) and B_g
    5. PDSAC      `pdsac.pdsac_bidirectional`: one rigid transform from both generated sets, and its other
                  distinct modes (`pdsac.distinct_modes`)
    6. candidates GenReg's estimate, PDSAC's other modes, the initial guess, the guard's refinement from
                  identity, the opt-in classical fallback (`fallback.fallback`), each refined (`refine.refine`:
                  the method of the refinement registry, `refinement.REFINEMENTS`)
    7. verify     `verify.Verifier`: overlap shares, agreement with the generated correspondences, the
                  calibrated probability of being right (`result.Confidence`)
    8. choose     `Registrar.choose`: the candidate that verifies best replaces the pose so far
    9. result     `Registrar.result` -> `result.build_result`: scores, covariance, unconstrained motions, the
                  confidence; input units; with `slide_fit`, a pose as well fitted slid along the source's main
                  axis (`Verifier.slid`: a road, a corridor) named and held (`Registrar.slide_checked`); with
                  `turn_fit`, one as well fitted turned about the source's z axis (`Verifier.turned`) likewise
                  (`Registrar.turn_checked`); with `see_through`, one whose source would have seen through the
                  target's structure (`Verifier.seen_through`) held (`Registrar.through_checked`)
   10. passes     `Registrar.more_passes`: while unsure, stages 1-9 again on other subsamples; the most probable wins
Conventions (frames, units, T_target_source): `genreg_core.geometry`. `transformation` is the input's
target_from_source; internally everything runs in the prepared pair's normalised frame.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
import torch

from genreg_core.checkpoint import load_checkpoint, resolve_checkpoint
from genreg_core.confidence import ConfidenceModel, feature_vector, load_beside
from genreg_core.config import OBJECT_MODEL, PDSACConfig, RefineConfig, RegistrationConfig
from genreg_core.errors import UncalibratedWarning
from genreg_core.fallback import fallback
from genreg_core.geometry import apply_transform
from genreg_core.pdsac import (
    MODE_TRANSLATION,
    both_directions,
    distinct_modes,
    pdsac_bidirectional,
    seeded_generator,
    union_correspondences,
)
from genreg_core.prepare import PreparedPair, model_frame_config, prepare_pair
from genreg_core.refine import guard_icp, refine
from genreg_core.refinement import refinement
from genreg_core.result import (
    SLIDE_SHARE,
    THROUGH_SHARE,
    TURN_SHARE,
    Confidence,
    RegistrationResult,
    as_well_fitted,
    as_well_turned,
    below_rival,
    build_result,
)
from genreg_core.verify import SLIDE_SPACINGS, Verifier

# With an initial guess, another pose replaces it only when its fitness (share of source points overlapping
# the target) is higher by more than this: a guess the user trusts is not traded for an equal-looking pose.
GUESS_MARGIN = 0.02
# Refinement from the guess replaces the guess only when it puts this much larger a share of the source
# within one target spacing (one spacing, not three, and a margin above refinement's slide from an exact
# guess: MODEL_CARD "Inference settings for robots").
REFINED_GUESS_MARGIN = 0.05


class Stopwatch:
    """Seconds per named pipeline stage, summed over the stage's runs: `with watch("refine"): ...`."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0


# The stages a result's `timings` name (seconds; a stage that did not run is absent): the per-stage cost table.
STAGES = ("prepare", "network", "pdsac", "refine", "verify", "modes", "guess", "guard", "fallback", "result",
          "passes")


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Torch's intra-op thread count at n inside the block (0: as it is), restored after (process-wide)."""
    previous = torch.get_num_threads()
    change = 0 < n != previous
    if change:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if change:
            torch.set_num_threads(previous)


@dataclass
class Estimate:
    """Stages 2-5 on a batch, in the normalised frame: b ~ transform a."""

    transform: torch.Tensor  # (B, 4, 4)
    source_generated: torch.Tensor  # A_g (B, N, 3), in b's frame
    target_generated: torch.Tensor  # B_g (B, N, 3), in a's frame
    inliers: torch.Tensor  # (B, 2N) bool: union correspondences within PDSAC's threshold of `transform`
    hypotheses: torch.Tensor  # (B, 2m, 4, 4): PDSAC's hypotheses of both directions (`pdsac.both_directions`)
    scores: torch.Tensor  # (B, 2m): their PDSAC scores (lower is better)
    overlap: torch.Tensor | None  # (B, 2N): the union correspondences' overlap weights (None: unweighted)

    @staticmethod
    def cat(parts: Sequence[Estimate]) -> Estimate:
        """One batch from several."""
        joined = [torch.cat([getattr(e, f) for e in parts]) for f in
                  ("transform", "source_generated", "target_generated", "inliers", "hypotheses", "scores")]
        overlap = None if parts[0].overlap is None else torch.cat([e.overlap for e in parts])
        return Estimate(*joined, overlap)

    def modes(self, k: int, a: np.ndarray, b: np.ndarray, pdsac: PDSACConfig) -> np.ndarray:
        """Pair k's other distinct modes (`pdsac.distinct_modes`, (modes - 1, 4, 4), float64) for its
        normalised network inputs `a`, `b` and the PDSAC settings in its frame."""
        src, dst = union_correspondences(torch.from_numpy(a)[None], self.source_generated[k: k + 1],
                                         torch.from_numpy(b)[None], self.target_generated[k: k + 1])
        weights = None if self.overlap is None else self.overlap[k: k + 1]
        with torch.inference_mode():
            modes = distinct_modes(self.transform[k: k + 1], self.hypotheses[k: k + 1], self.scores[k: k + 1],
                                   src, dst, pdsac, weights)
        return modes[0].double().cpu().numpy()


WARM_UP_POINTS = 20_000  # points per cloud of `Registrar.warm_up`'s synthetic pair


def warm_up_config(config: RegistrationConfig) -> RegistrationConfig:
    """`config` with PDSAC's modes searched whatever the confidence: a warm-up pair runs their path too."""
    return replace(config, pdsac=replace(config.pdsac, modes_below=1.0))


def warm_up_pair(points: int = WARM_UP_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """A deterministic synthetic (source, target) pair, float32, metres: a 4 m room corner (floor, two walls) with
    a box, the target seen from a pose 10 deg and 0.2 m away."""
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0.0, 4.0, (2, points))
    face = rng.integers(0, 4, points)
    box = np.stack([1.5 + 0.5 * (u % 1.0), 1.5 + 0.5 * (v % 1.0), 0.5 * rng.uniform(0.0, 1.0, points)], axis=1)
    cloud = np.where((face == 0)[:, None], np.stack([u, v, 0 * u], axis=1),
                     np.where((face == 1)[:, None], np.stack([u, 0 * u, 0.6 * v], axis=1),
                              np.where((face == 2)[:, None], np.stack([0 * u, v, 0.6 * u], axis=1), box)))
    angle = np.radians(10.0)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    T[:3, 3] = (0.2, -0.1, 0.05)
    return cloud.astype(np.float32), apply_transform(T, cloud).astype(np.float32)


COARSE_POINTS = 1000  # `verified_mode` refines the other modes on this many source points first
COARSE_ITERATIONS = 10  # ... with this many ICP iterations


@dataclass
class Choice:
    """Where a pair's candidates settled (stage 8): the pose (normalised frame, b ~ T a), what it grew from
    (`result.STARTS`), the inlier ratio of the generated correspondences under it, and its rival: two
    distinct poses cannot both be right, so P(this one) <= 1 - P(the rival)."""

    transform: np.ndarray
    start: str
    inlier_ratio: float
    rival: float = 0.0  # the probability that another, distinct pose is right (the best other mode's)


def distinct_poses(T_a: np.ndarray, T_b: np.ndarray, separation_rad: float, translation: float = MODE_TRANSLATION
                   ) -> bool:
    """Whether two poses are distinct modes: rotations more than `separation_rad` apart, or translations more
    than `translation` (default `pdsac.MODE_TRANSLATION`: the normalised frame's; times `PreparedPair.scale`
    in input units)."""
    cos = (np.trace(T_a[:3, :3].T @ T_b[:3, :3]) - 1.0) / 2.0
    return bool(cos < np.cos(separation_rad) or np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) > translation)


def coarsely(dense_src: np.ndarray, target: object, refine_cfg: RefineConfig) -> Callable[[np.ndarray], np.ndarray]:
    """The refinement of a start on `COARSE_POINTS` of the source's points for `COARSE_ITERATIONS` iterations, no
    tight stage: how PDSAC's other modes (`verified_mode`) and turned poses (`Registrar.turn_checked`) are first
    aligned."""
    coarse_src = dense_src[:: max(1, len(dense_src) // COARSE_POINTS)]
    coarse_cfg = replace(refine_cfg, max_iterations=min(COARSE_ITERATIONS, refine_cfg.max_iterations), fine_fraction=1.0)
    return lambda start: refine(coarse_src, target, start, coarse_cfg)


def verified_mode(check: Verifier, target: object, T_best: np.ndarray, best_score: float, start: np.ndarray,
                  find_modes: Callable[[], np.ndarray], refine_cfg: RefineConfig) -> tuple[np.ndarray, float]:
    """GenReg's refined estimate `T_best` (calibrated probability `best_score`) or another PDSAC mode
    (`find_modes()`: `Estimate.modes`, (K, 4, 4)), whichever is more probably right (`Verifier.probability`).
    Each mode other than `T_best`'s `start` is refined coarsely (`COARSE_POINTS` source points,
    `COARSE_ITERATIONS` iterations), the best of them fully; it replaces `T_best` only if it then verifies
    better. Without refinement ("none") the modes are compared as they are. Returns the pose and its rival's
    probability: the best of the other distinct poses verified."""
    modes = find_modes()
    dense_src = check.pair.dense_src
    distinct = [M for k, M in enumerate(modes) if not any(np.array_equal(M, m) for m in [start, *modes[:k]])]
    coarse = list(map(coarsely(dense_src, target, refine_cfg), distinct))
    scores = [check.probability(T) for T in coarse]
    chosen = T_best
    if scores and max(scores) > best_score:
        best = int(np.argmax(scores))
        rival = refine(dense_src, target, coarse[best], refine_cfg)
        chosen = rival if check.probability(rival) > best_score else T_best
    separation = np.radians(check.separation)
    # the rival: the most probable candidate that stayed a distinct pose (modes often refine to one answer)
    others = [score for T, score in zip([T_best, *coarse], [best_score, *scores], strict=True)
              if distinct_poses(T, chosen, separation)]
    return chosen, max(others, default=0.0)


class Registrar:
    """A loaded GenReg model plus its registration settings and its checkpoint's confidence calibration.
    Thread-compatible, not thread-safe.

    A registrar whose calibration does not serve its refinement (`refine.method`; no calibration at all
    included) is uncalibrated: its confidence is the overlap score, PDSAC's other modes and more passes are
    off (`genreg_core.result`). It warns so (`errors.UncalibratedWarning`) when it is built and whenever its
    settings change to such a refinement; it does not refuse them."""

    def __init__(self, model: torch.nn.Module, config: RegistrationConfig | None = None,
                 calibration: ConfidenceModel | None = None) -> None:
        self.calibration = calibration  # P(success) from the verification (None: the checkpoint has none)
        self._config: RegistrationConfig | None = None
        self.config = config or RegistrationConfig()
        self.model = model.to(self.config.device).eval()

    @property
    def config(self) -> RegistrationConfig:
        """The settings the next registration uses."""
        assert self._config is not None
        return self._config

    @config.setter
    def config(self, config: RegistrationConfig) -> None:
        method = config.refine.method
        changed = self._config is None or self._config.refine.method != method
        self._config = config
        if changed and not self.calibrated:
            reason = ("the checkpoint has no confidence calibration" if self.calibration is None else
                      f"the checkpoint's confidence calibration has no model for refine.method {method!r} (it has "
                      f"{', '.join(sorted(self.calibration.by_refinement))})")
            warnings.warn(f"uncalibrated confidence: {reason}; the confidence is the overlap score, and PDSAC's "
                          "other modes and more network passes are off", UncalibratedWarning, stacklevel=3)

    @classmethod
    def from_checkpoint(
        cls, name_or_path: str | os.PathLike = OBJECT_MODEL, config: RegistrationConfig | None = None,
        num_points: int | None = None,
    ) -> Registrar:
        """Load a shipped model by name or a checkpoint file, with the confidence calibration beside it
        (`genreg_core.confidence`); CheckpointError if unusable."""
        config = config or RegistrationConfig()
        model, _ = load_checkpoint(name_or_path, num_points=num_points, device=config.device)
        return cls(model, config, load_beside(resolve_checkpoint(name_or_path)))

    @property
    def confidence(self) -> Confidence:
        """How this registrar's confidence is worked out: the calibration's model for its refinement."""
        method = refinement(self.config.refine.method)
        return Confidence(self.calibration if method.calibrated else None, method.name)

    @property
    def calibrated(self) -> bool:
        """Whether the confidence is the calibration's probability: a calibration fitted for this refinement."""
        return self.confidence.calibrated

    @property
    def num_points(self) -> int:
        return self.model.config.num_points

    def warm_up(self, points: int = WARM_UP_POINTS) -> None:
        """Run one synthetic pair (`warm_up_pair`) through every stage of this registrar's settings, PDSAC's modes
        included, so that first-call costs (allocations, thread pools, kernels loaded from numba's cache, lazy
        imports) are paid before the first real pair. Changes no setting and no later result."""
        config = self.config
        self.config = warm_up_config(config)
        try:
            self.register(*warm_up_pair(points))
        finally:
            self.config = config

    def register(
        self, source: np.ndarray, target: np.ndarray, initial_guess: np.ndarray | None = None
    ) -> RegistrationResult:
        """Register `source` onto `target`; `initial_guess` is a 4x4 target_from_source to start from."""
        return self.register_many([(source, target, initial_guess)])[0]

    def register_many(self, pairs: Sequence[tuple[np.ndarray, ...]]) -> list[RegistrationResult]:
        """Register (source, target) or (source, target, initial_guess) pairs with one batched network +
        PDSAC pass (throughput); each pair is prepared, refined and scored on its own, as in `register`.
        Every pair is subsampled with the config's seed; PDSAC draws for the whole batch from one
        generator. The batch's network and PDSAC seconds are shared out equally. A bad pair raises
        before anything runs."""
        cfg = self.config
        prepared = [self.prepare(*pair) for pair in pairs]  # 1. prepare
        if not prepared:
            return []
        a = torch.from_numpy(np.stack([p.a for p in prepared])).to(cfg.device)
        b = torch.from_numpy(np.stack([p.b for p in prepared])).to(cfg.device)
        gen = seeded_generator(cfg.seed)
        stages: dict[str, float] = {}
        frames = [model_frame_config(cfg, p.scale).pdsac for p in prepared]  # distances per pair's frame
        if len({f.inlier_threshold for f in frames}) == 1:
            est = self.estimate(a, b, gen, stages, frames[0])  # 2.-5. encode, interact, generate, PDSAC
        else:  # metric thresholds on pairs of different scales: one PDSAC threshold per pair
            est = Estimate.cat([self.estimate(a[k: k + 1], b[k: k + 1], gen, stages, f) for k, f in enumerate(frames)])
        shared = {name: seconds / len(prepared) for name, seconds in stages.items()}
        results = [self.refine_and_score(p, est, k, shared) for k, p in enumerate(prepared)]  # 6.-9.
        return [self.more_passes(pair, p, r) for pair, p, r in zip(pairs, prepared, results, strict=True)]  # 10.

    def more_passes(self, pair: tuple[np.ndarray, ...], p: PreparedPair, first: RegistrationResult
                    ) -> RegistrationResult:
        """Stage 10 for one pair: while the first pass is unsure (calibrated, no initial guess, confidence below
        `pdsac.modes_below`), up to `passes - 1` more, each on another subsample with other PDSAC draws (seed +
        j). The result the calibration finds most probably right wins; the most probable other result that is a
        distinct pose is its rival (its confidence is at most 1 - the rival's). Seconds of every pass count:
        the winner's stages are the first pass's, 'passes' the others' seconds."""
        cfg = self.config
        if cfg.passes <= 1 or not self.calibrated or p.init is not None or first.confidence >= cfg.pdsac.modes_below:
            return first
        seeds = [None if cfg.seed is None else cfg.seed + j for j in range(1, cfg.passes)]
        t0 = time.perf_counter()
        results = [first, *(Registrar(self.model, replace(cfg, seed=seed, passes=1), self.calibration)
                            .register(*pair) for seed in seeds)]
        confidence = self.confidence
        scores = [confidence.probability(feature_vector(r.verification)) for r in results]
        best = results[int(np.argmax(scores))]
        separation = np.radians(cfg.pdsac.mode_separation)
        rival = max((score for r, score in zip(results, scores, strict=True)
                     if distinct_poses(r.transformation, best.transformation, separation,
                                     MODE_TRANSLATION * p.scale)), default=0.0)
        more = time.perf_counter() - t0
        timings = first.timings | {"passes": more, "total": first.timings["total"] + more}
        return replace(best, confidence=below_rival(best.confidence, rival), timings=timings, passes=len(results))

    def prepare(self, source: np.ndarray, target: np.ndarray, initial_guess: np.ndarray | None = None
                ) -> PreparedPair:
        """Stage 1 with this registrar's N, refinement size, minimum size and seed."""
        cfg = self.config
        return prepare_pair(source, target, initial_guess, num_points=self.num_points,
                            refine_points=cfg.refine.num_points, min_points=cfg.min_points, seed=cfg.seed)

    @torch.inference_mode()
    def estimate(self, a: torch.Tensor, b: torch.Tensor, generator: torch.Generator | None = None,
                 timings: dict[str, float] | None = None, pdsac: PDSACConfig | None = None) -> Estimate:
        """Stages 2-5 on normalised (B, N, 3) batches, with `pdsac` settings in that frame (default: the
        config's, for inputs already in the unit box); seconds of the network and of PDSAC are added to
        `timings` ('network', 'pdsac') if given."""
        pdsac = pdsac or model_frame_config(self.config, 1.0).pdsac
        with torch_threads(self.config.estimate_threads):
            t0 = time.perf_counter()
            enc = self.model.encode(a, b)  # 2. encode
            match = self.model.interact(enc)  # 3. interact
            out = self.model.generate(enc, match)  # 4. generate
            t1 = time.perf_counter()
            overlap = out.overlap()
            T, res_a, res_b, inliers = pdsac_bidirectional(  # 5. PDSAC
                a, out.source_generated, b, out.target_generated, pdsac, generator, overlap)
            hypotheses, scores = both_directions(res_a, res_b)  # its other modes, when asked (Estimate.modes)
        if timings is not None:
            timings["network"] = timings.get("network", 0.0) + t1 - t0
            timings["pdsac"] = timings.get("pdsac", 0.0) + time.perf_counter() - t1
        return Estimate(T, out.source_generated, out.target_generated, inliers, hypotheses, scores,
                        None if overlap is None else torch.cat(overlap, dim=1))

    def refine_and_score(self, p: PreparedPair, est: Estimate, k: int, shared: dict[str, float]
                         ) -> RegistrationResult:
        """Stages 6-9 for pair k of a batch estimate: the candidates, refined and verified, the choice and
        the result. `shared`: the batch's network and PDSAC seconds per pair."""
        cfg = model_frame_config(self.config, p.scale)  # distances in this pair's normalised frame
        watch = Stopwatch()
        check = Verifier(p, est.source_generated[k], est.target_generated[k], cfg.pdsac.tau,  # 7. verify
                         self.confidence, cfg.pdsac.mode_separation)
        choice = self.choose(p, est, k, check, cfg, watch)  # 6.-8. candidates, refine, verify, choose
        with watch("result"):
            result = self.result(p, est, k, check, choice, cfg)  # 9. result
        timings = {"prepare": p.seconds, **shared, **watch.seconds}
        result.timings = timings | {"total": sum(timings.values())}
        return result

    def choose(self, p: PreparedPair, est: Estimate, k: int, check: Verifier, cfg: RegistrationConfig,
               watch: Stopwatch) -> Choice:
        """Stages 6 (candidates, refined) to 8 (choose), in the pair's normalised frame `cfg`, each stage's
        seconds in `watch`: GenReg's estimate, refined ('refine'); its calibrated probability ('verify': with
        a calibration, no guess and `pdsac.modes_below` above 0; a guess asks for a local answer); PDSAC's other
        modes only when that is below `pdsac.modes_below` ('modes': a confident estimate costs nothing more); the
        initial guess, kept
        or refined ('guess': another pose replaces it only with a `GUESS_MARGIN` more fitness); without a
        guess, the guard's wide refinement from identity when the overlap score is below `refine.guard_below`
        ('guard'); the opt-in classical fallback below `fallback.below` ('fallback'). The guard and the
        fallback replace the pose so far when they seat more of the source within one spacing."""
        method = refinement(cfg.refine.method)
        target = getattr(p, method.target)  # the target in the form the refinement needs
        winner = est.transform[k].double().cpu().numpy()
        with watch("refine"):
            T = refine(p.dense_src, target, winner, cfg.refine)
        choice = Choice(T, "genreg", float(est.inliers[k].float().mean()))
        if check.confidence.calibrated and p.init is None and cfg.pdsac.modes_below > 0:
            with watch("verify"):
                score = check.probability(T)
            if score < cfg.pdsac.modes_below:
                def modes() -> np.ndarray:
                    with torch_threads(cfg.estimate_threads):
                        return est.modes(k, p.a, p.b, cfg.pdsac)

                with watch("modes"):
                    mode, rival = verified_mode(check, target, T, score, winner, modes, cfg.refine)
                choice = Choice(mode, "genreg", choice.inlier_ratio if mode is T else check.agreement(mode), rival)
        if p.init is not None:  # the initial guess: identity in the guess-moved frame
            with watch("guess"):
                kept = np.eye(4)
                if method.refines:  # refinement must earn its move away from the user's guess, at one spacing
                    moved = refine(p.dense_src, target, kept, cfg.refine)
                    kept = moved if check.closer(moved, kept, REFINED_GUESS_MARGIN) else kept
                if check.fitness(kept)[0] + GUESS_MARGIN > check.fitness(choice.transform)[0]:
                    choice = Choice(kept, "initial_guess", check.agreement(kept))
        elif method.refines and check.overlap_score(choice.transform, choice.inlier_ratio) < cfg.refine.guard_below:
            with watch("guard"):
                guarded = guard_icp(p.dense_src, target, cfg.refine)
                if check.closer(guarded, choice.transform):
                    choice = Choice(guarded, "guard", check.agreement(guarded))
        if cfg.fallback.method != "none" and check.overlap_score(choice.transform, choice.inlier_ratio) < cfg.fallback.below:
            with watch("fallback"):
                rescue = fallback(p.dense_src, p.dense_tgt, cfg.fallback)
                rescue = refine(p.dense_src, target, rescue, cfg.refine)
                if check.closer(rescue, choice.transform):
                    choice = Choice(rescue, "fallback", check.agreement(rescue))
        return choice

    def result(self, p: PreparedPair, est: Estimate, k: int, check: Verifier, choice: Choice, cfg: RegistrationConfig
               ) -> RegistrationResult:
        """Stage 9: the chosen pose verified (`Verifier.verify`, `Verifier.aligned`) into its result
        (`result.build_result`), in input units (`timings` are filled in by the caller), then checked for slides, turns
        and what it sees through (`slide_checked`, `turn_checked`, `through_checked`; `cfg`: the pair's normalised-frame
        settings)."""
        T_n = choice.transform
        T = p.to_input_units(T_n)
        origin_n = (T[:3, 3] - p.offset) / p.scale  # the pose's position, normalised frame
        a_gen = p.points_to_input_units(est.source_generated[k].double().cpu().numpy())
        b_gen = p.points_to_input_units(est.target_generated[k].double().cpu().numpy())
        result = build_result(
            T, check.verify(T_n, choice.inlier_ratio, choice.rival), check.aligned(T_n, origin_n), check.confidence,
            start=choice.start,
            aligned_source=p.aligned_source(T),  # float32, one product
            source_valid_mask=p.src_mask,
            source_generated=a_gen.astype(np.float32),
            target_generated=apply_transform(np.linalg.inv(p.guess), b_gen).astype(np.float32),
        )
        return self.through_checked(self.turn_checked(self.slide_checked(result, check, T_n, p.scale), check, T_n, p, cfg),
                                    check)

    def slide_checked(self, result: RegistrationResult, check: Verifier, T_n: np.ndarray, scale: float
                      ) -> RegistrationResult:
        """With `slide_fit`, a result whose source seats as well moved along its main axis (`Verifier.slid`: a road
        or a corridor alike along its length, where a pose slid metres along it fits as well as the right one)
        named as well fitted along it (`result.as_well_fitted`) and held at 1 - its confidence; the slid share in
        its `verification` (`result.SLIDE_SHARE`)."""
        fit = self.config.slide_fit
        if fit <= 0:
            return result
        axis, share = check.slid(T_n)
        result.verification[SLIDE_SHARE] = share
        if share < fit:
            return result
        held = as_well_fitted(result, axis * SLIDE_SPACINGS * check.pair.target_index.spacing * scale)
        return replace(held, confidence=below_rival(held.confidence, held.confidence))

    def turn_checked(self, result: RegistrationResult, check: Verifier, T_n: np.ndarray, p: PreparedPair,
                     cfg: RegistrationConfig) -> RegistrationResult:
        """With `turn_fit`, a confident result (above 0.5) whose source seats as well at a distinct pose turned about
        its z axis and refined again (`Verifier.turned`: a corridor or a hall alike turned around, where the fit does
        not tell which way the source faces) named (`result.as_well_turned`) and held at 1 - its confidence; the
        turned share in its `verification` (`result.TURN_SHARE`). Only a result above 0.5 is checked (holding changes no
        other): one held already (a slide) is not, nor one registered from an initial guess (the guess says which way
        the source faces). The turns are aligned coarsely, as PDSAC's other modes are."""
        if self.config.turn_fit <= 0 or result.confidence <= 0.5 or p.init is not None:
            return result
        target = getattr(p, refinement(cfg.refine.method).target)
        T = result.transformation
        up = T[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the source's z axis (a level sensor's up, REP-103)
        rival, share = check.turned(T_n, up, (T[:3, 3] - p.offset) / p.scale, coarsely(p.dense_src, target, cfg.refine))
        result.verification[TURN_SHARE] = share
        if share < self.config.turn_fit:
            return result
        held = as_well_turned(result, p.to_input_units(rival), up)
        return replace(held, confidence=below_rival(held.confidence, held.confidence))

    def through_checked(self, result: RegistrationResult, check: Verifier) -> RegistrationResult:
        """With `see_through`, a confident result (above 0.5: holding changes no other) whose source, placed by it, would
        have seen through at least `see_through` of the target's structure (`Verifier.seen_through`: walls in front of
        the source's returns, as where a corridor's pose is turned or slid and its doorways face walls) held at 1 - its
        confidence; the share in its `verification` (`result.THROUGH_SHARE`). It names no motion: no motion of the pose
        explains what it contradicts."""
        if self.config.see_through <= 0 or result.confidence <= 0.5:
            return result
        share = check.seen_through(result.transformation)
        result.verification[THROUGH_SHARE] = share
        if share < self.config.see_through:
            return result
        return replace(result, confidence=below_rival(result.confidence, result.confidence))
