"""The registration API every other part of genreg calls.

    reg = Registrar.from_checkpoint("modelnet40")
    result = reg.register(source, target)          # (N, 3) and (M, 3) arrays, any units
    target_points ~ apply_transform(result.transformation, source_points)

Conventions: `transformation` is 4x4, column vectors, target_from_source: x_t = R x_s + t, in the
input's units. The source is moved into the target's frame. Internally both clouds are resampled to
the model's N and normalised jointly by one similarity taken from the source's bounding box (the
source fills the unit box, as in training); the result is mapped back to input units.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
import torch
from scipy.spatial import cKDTree

from genreg_core.checkpoint import load_checkpoint
from genreg_core.config import RefineConfig, RegistrationConfig
from genreg_core.errors import InvalidPointCloudError, NonFinitePointsError, TooFewPointsError
from genreg_core.geometry import apply_transform, denormalize_transform, unit_box_normalization
from genreg_core.model.genreg import GenRegNet
from genreg_core.pdsac import register_batch, union_inlier_share


@dataclass
class RegistrationResult:
    """Result of one registration. Transform and clouds are in the input's units."""

    transformation: np.ndarray  # (4, 4) float64, target_from_source
    source_generated: np.ndarray  # A_g: (n, 3) model-resolution source generated in the target frame
    target_generated: np.ndarray  # B_g: (n, 3) model-resolution target generated in the source frame
    aligned_source: np.ndarray  # (K, 3) float32: the finite source points, input order, in target frame
    source_valid_mask: np.ndarray  # (N,) bool: which input source rows were finite (and kept)
    fitness: float  # share of sampled source points with a target point within 3x the target's spacing
    inlier_ratio: float  # fraction of generated correspondences (both directions) consistent with T
    inlier_rmse: float  # RMS distance of the fitness inliers, input units
    confidence: float  # in [0, 1]: geometric mean of fitness and inlier_ratio
    start: str = "genreg"  # what the final pose grew from: "genreg", or "initial_guess" (the refine guard won)
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage and 'total'


def validate_cloud(points: object, name: str, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Check an (N, 3) real array; return (finite points as float64, finite-row mask).

    Raises InvalidPointCloudError (shape/dtype), NonFinitePointsError (no finite point) or
    TooFewPointsError (fewer than `min_points` finite points).
    """
    if not isinstance(points, np.ndarray):
        if isinstance(points, torch.Tensor):
            points = points.detach().cpu().numpy()
        else:
            raise InvalidPointCloudError(f"{name} must be a numpy array of shape (N, 3), got {type(points).__name__}")
    if points.dtype.kind not in "fiu" or points.dtype == np.float16:
        raise InvalidPointCloudError(f"{name} must hold float32/float64 (or integer) values, got dtype {points.dtype}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidPointCloudError(f"{name} must have shape (N, 3), got {points.shape}")
    mask = np.isfinite(points).all(axis=1)
    count = int(mask.sum())
    if count == 0:
        raise NonFinitePointsError(f"{name} has no finite points ({len(points)} given, all NaN/Inf or empty)")
    if count < min_points:
        raise TooFewPointsError(f"{name} has {count} finite points; registration needs at least {min_points}")
    return points[mask].astype(np.float64, copy=False), mask


def subsample(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random points: without replacement if there are enough, else all points plus repeats."""
    if len(points) >= n:
        return points[rng.choice(len(points), n, replace=False)]
    extra = rng.choice(len(points), n - len(points), replace=True)
    return points[rng.permutation(np.concatenate([np.arange(len(points)), extra]))]


class Registrar:
    """A loaded GenReg model plus its registration settings. Thread-compatible, not thread-safe."""

    def __init__(self, model: GenRegNet, config: RegistrationConfig | None = None) -> None:
        self.config = config or RegistrationConfig()
        self.model = model.to(self.config.device).eval()

    @classmethod
    def from_checkpoint(
        cls,
        name_or_path: str | os.PathLike = "modelnet40",
        config: RegistrationConfig | None = None,
        num_points: int | None = None,
    ) -> Registrar:
        """Load a shipped model by name or a checkpoint file; CheckpointError if unusable."""
        config = config or RegistrationConfig()
        model, _ = load_checkpoint(name_or_path, num_points=num_points, device=config.device)
        return cls(model, config)

    @property
    def num_points(self) -> int:
        return self.model.config.num_points

    def register(
        self, source: np.ndarray, target: np.ndarray, initial_guess: np.ndarray | None = None
    ) -> RegistrationResult:
        """Register `source` onto `target`; `initial_guess` is a 4x4 target_from_source to start from."""
        return self.register_many([(source, target, initial_guess)])[0]

    def register_many(self, pairs: Sequence[tuple[np.ndarray, ...]]) -> list[RegistrationResult]:
        """Register (source, target) or (source, target, initial_guess) pairs with one batched network +
        PDSAC pass (throughput); each pair is prepared, refined and checked on its own, as in `register`
        (one pair: exactly `register`). Every pair is subsampled with the config's seed; PDSAC draws for
        the whole batch from one generator. Timings: the batch's network and PDSAC seconds are shared out
        equally, the other stages are the pair's own. A bad pair raises before anything runs.
        """
        cfg = self.config
        prepared = [self._prepare(*pair) for pair in pairs]
        if not prepared:
            return []
        device = cfg.device
        a = torch.from_numpy(np.stack([p.a for p in prepared])).to(device)
        b = torch.from_numpy(np.stack([p.b for p in prepared])).to(device)
        with torch.no_grad():
            gen = torch.Generator().manual_seed(cfg.seed) if cfg.seed is not None else None
            stages: dict[str, float] = {}
            T_n, out, inliers, last_start = register_batch(self.model, a, b, cfg.pdsac, cfg.passes, gen, stages)
        shared = {name: seconds / len(prepared) for name, seconds in stages.items()}
        return [
            self._finish(p, T_n[k], a[k : k + 1], b[k : k + 1], out.source_generated[k : k + 1],
                         out.target_generated[k : k + 1], inliers[k], last_start[k], shared)
            for k, p in enumerate(prepared)
        ]

    def _prepare(
        self, source: np.ndarray, target: np.ndarray, initial_guess: np.ndarray | None = None
    ) -> _PreparedPair:
        cfg = self.config
        t0 = time.perf_counter()
        src, src_mask = validate_cloud(source, "source", cfg.min_points)
        tgt, _ = validate_cloud(target, "target", cfg.min_points)
        init = np.eye(4) if initial_guess is None else _check_transform(initial_guess)
        rng = np.random.default_rng(cfg.seed)
        src_init = src if initial_guess is None else apply_transform(init, src)
        offset, scale = unit_box_normalization(src_init)  # one similarity for both clouds

        def normalized_subset(points: np.ndarray, n: int, keep_all: bool = False) -> np.ndarray:
            chosen = points if keep_all and len(points) <= n else subsample(points, n, rng)
            return ((chosen - offset) / scale).astype(np.float32)

        a = normalized_subset(src_init, self.num_points)
        b = normalized_subset(tgt, self.num_points)
        dense_src = normalized_subset(src_init, cfg.refine.num_points, keep_all=True)
        dense_tgt = normalized_subset(tgt, cfg.refine.num_points, keep_all=True)
        return _PreparedPair(src, src_mask, init, offset, scale, a, b, dense_src, dense_tgt,
                             time.perf_counter() - t0)

    def _finish(
        self, p: _PreparedPair, T_n_t: torch.Tensor, a: torch.Tensor, b: torch.Tensor, a_gen: torch.Tensor,
        b_gen: torch.Tensor, inliers: torch.Tensor, last_start_t: torch.Tensor, shared: dict[str, float],
    ) -> RegistrationResult:
        """Refinement, guard, fitness and mapping back of one pair (tensors of batch 1 / unbatched)."""
        cfg = self.config
        t3 = time.perf_counter()
        T_n = T_n_t.double().cpu().numpy()
        last_start = last_start_t.double().cpu().numpy()
        # The last pass saw the source moved by `last_start` (and the initial guess): B_g is in that frame.
        back = np.linalg.inv(denormalize_transform(last_start, p.offset, p.scale) @ p.init)
        if cfg.refine.method != "none":
            T_n = refine_icp(p.dense_src, p.dense_tgt, T_n, cfg.refine)
        fitness_distance = FITNESS_SPACINGS * point_spacing(p.dense_tgt)
        fitness, rmse_n = overlap_fitness(p.dense_src, p.dense_tgt, T_n, fitness_distance)
        inlier_ratio = float(inliers.float().mean())
        start = "genreg"
        if cfg.refine.method != "none" and np.sqrt(fitness * inlier_ratio) < cfg.refine.guard_below:
            T_prior = guard_icp(p.dense_src, p.dense_tgt, cfg.refine)
            fitness_prior, rmse_prior = overlap_fitness(p.dense_src, p.dense_tgt, T_prior, fitness_distance)
            if fitness_prior > fitness:
                T_n, fitness, rmse_n, start = T_prior, fitness_prior, rmse_prior, "initial_guess"
                # the generated correspondences of the last pass relate start-moved A to B
                T_k = torch.from_numpy(T_prior @ np.linalg.inv(last_start))[None].to(a.dtype)
                moved = apply_transform(last_start_t[None].to(a.dtype), a)
                inlier_ratio = float(union_inlier_share(
                    T_k, moved, a_gen, b, b_gen, cfg.pdsac.inlier_threshold)[0])
        t4 = time.perf_counter()
        T = denormalize_transform(T_n, p.offset, p.scale) @ p.init
        aligned = apply_transform(T, p.src).astype(np.float32)
        a_gen_np = a_gen[0].double().cpu().numpy() * p.scale + p.offset
        b_gen_np = b_gen[0].double().cpu().numpy() * p.scale + p.offset
        t5 = time.perf_counter()
        return RegistrationResult(
            transformation=T,
            source_generated=a_gen_np.astype(np.float32),
            target_generated=apply_transform(back, b_gen_np).astype(np.float32),
            aligned_source=aligned,
            source_valid_mask=p.src_mask,
            fitness=fitness,
            inlier_ratio=inlier_ratio,
            inlier_rmse=rmse_n * p.scale,
            confidence=float(np.sqrt(fitness * inlier_ratio)),
            start=start,
            timings={
                "preprocess": p.seconds,
                "network": shared["network"],
                "pdsac": shared["pdsac"],
                "refine": t4 - t3,
                "postprocess": t5 - t4,
                "total": p.seconds + shared["network"] + shared["pdsac"] + t5 - t3,
            },
        )


@dataclass(frozen=True)
class _PreparedPair:
    """One pair ready for the network: finite source, its mask, the initial guess, the similarity
    (normalised = (x - offset) / scale), the model-N clouds a, b and the refinement clouds, normalised."""

    src: np.ndarray
    src_mask: np.ndarray
    init: np.ndarray
    offset: np.ndarray
    scale: float
    a: np.ndarray
    b: np.ndarray
    dense_src: np.ndarray
    dense_tgt: np.ndarray
    seconds: float


def _check_transform(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidPointCloudError(f"initial_guess must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InvalidPointCloudError("initial_guess must be a proper rigid transform (orthonormal R, det +1)")
    return T


def _o3d_cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


FITNESS_SPACINGS = 3.0  # fitness counts a source point as overlapping within this many target spacings


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest neighbour in the same cloud (its sampling density)."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


def overlap_fitness(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, threshold: float) -> tuple[float, float]:
    """Open3D's fitness (share of moved source points with a target point within `threshold`) and RMSE."""
    ev = o3d.pipelines.registration.evaluate_registration(_o3d_cloud(src), _o3d_cloud(tgt), threshold, T)
    return float(ev.fitness), float(ev.inlier_rmse)


def guard_icp(src: np.ndarray, tgt: np.ndarray, cfg: RefineConfig) -> np.ndarray:
    """The refinement guard's candidate: ICP from the initial guess (identity in the normalised frame of
    the guess-moved source) with the guard's cut-off and iterations, unit-box units."""
    guard = replace(cfg, max_correspondence_distance=cfg.guard_distance, max_iterations=cfg.guard_iterations)
    return refine_icp(src, tgt, np.eye(4), guard)


def refine_icp(src: np.ndarray, tgt: np.ndarray, T_init: np.ndarray, cfg: RefineConfig) -> np.ndarray:
    """A few Open3D ICP iterations from T_init (unit-box units), point-to-point or point-to-plane."""
    reg = o3d.pipelines.registration
    source, target = _o3d_cloud(src), _o3d_cloud(tgt)
    if cfg.method == "point_to_plane":
        target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        estimation = reg.TransformationEstimationPointToPlane()
    else:
        estimation = reg.TransformationEstimationPointToPoint()
    result = reg.registration_icp(
        source, target, cfg.max_correspondence_distance, T_init, estimation,
        reg.ICPConvergenceCriteria(max_iteration=cfg.max_iterations),
    )
    return np.asarray(result.transformation)
