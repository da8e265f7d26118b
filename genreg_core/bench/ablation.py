"""Issue 5's ablations: the pose solver (PDSAC against Open3D's RANSAC on the same generated
correspondences) and the backbone (PointMixer against DGCNN-only and PointNet++-style encoders, trained
on the same budget).

Backbone (`run_backbone_dataset`): each named checkpoint registers every pair as the API's `genreg`
method does (network, then `pdsac_bidirectional`); records hold RE, TE, CD and success as in the suites,
`seconds` = network + PDSAC, and the generation quality of the paper's ablation tables: `gen_cd`, the
Chamfer distance, and `gen_mse`, the mean squared point error |A_g,i - T_gt A_i|^2, between the generated
A_g and the truly moved source T_gt A (the N network inputs, dataset units).

Pose solver:

Per pair the GenReg network runs once, on inputs prepared as `Registrar.register` prepares them (source
and target resampled to the model's N with the config's seed, one similarity from the source's bounding
box), so the `pdsac` row reproduces the suite's `genreg` method. Every solver then estimates T_BA
(4x4, column vectors, target_from_source: b ~ R a + t) in normalised units from the union of the
correspondences {A_i -> A_g,i} and {B_g,i -> B_i}, which all obey B-frame = T_BA A-frame (see `pdsac`):
- `pdsac`: `pdsac_bidirectional` with the RegistrationConfig's settings (m hypotheses of k points per
  direction, truncated-residual score on the union, least-squares refit on the union's inliers);
- `o3d-ransac`: Open3D `registration_ransac_based_on_correspondence` on the union: inlier distance =
  PDSAC's inlier_threshold, point-to-point (Kabsch) estimation, no checkers, best inlier count (then
  RMSE) wins, early exit at the criteria's confidence; it returns the best minimal-sample transform.
  Seeded through `o3d.utility.random.seed`, its results still vary slightly from run to run (seen with
  Open3D 0.20 at one thread; isl-org/Open3D#7475), while PDSAC's are bit-reproducible;
- `o3d-ransac+refit`: that transform refit on its inliers by PDSAC's least squares (`refit_on_inliers`),
  which separates the hypothesis search from the final refit.
The estimate is mapped back to the dataset's units and scored like the suites (RE deg, TE, CD, success).
`seconds` is the solver's wall time alone (inputs already in memory, Open3D's conversions included),
after one untimed warm-up; the network time is stored apart (`network_seconds` per pair).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from typing import Any

import numpy as np
import open3d as o3d
import torch
from tqdm import tqdm

from genreg_core.bench.suites import (
    DEFAULT_CHECKPOINTS,
    OBJECT,
    BenchOptions,
    BenchRun,
    DatasetSpec,
    Suite,
    _cd_subset,
    evaluate,
    failure_fields,
    plan_pairs,
    resolve_suite,
    run_meta,
)
from genreg_core.config import PDSACConfig, RegistrationConfig
from genreg_core.errors import CheckpointError
from genreg_core.geometry import apply_transform, denormalize_transform, unit_box_normalization
from genreg_core.metrics import chamfer_distance
from genreg_core.pdsac import pdsac_bidirectional, refit_on_inliers, union_correspondences, union_inlier_share
from genreg_core.registration import Registrar, subsample, validate_cloud

reg = o3d.pipelines.registration

POSE_SOLVER = "pose-solver"
POSE_SOLVER_TITLE = "Ablation: pose solver (same generated correspondences)"
BACKBONE = "backbone"
BACKBONE_TITLE = "Ablation: backbone (same training budget)"
ABLATIONS = (POSE_SOLVER, BACKBONE)
# `scripts/ablation_backbone.sh` trains these (config/train_modelnet40_ppf.yaml, model.backbone = name)
DEFAULT_BACKBONES = {name: f"runs/abl_{name}/last.pt" for name in ("pointmixer", "dgcnn", "pointnet2")}


@dataclass(frozen=True)
class Correspondences:
    """GenReg's generated correspondences of one pair, normalised units, (1, N, 3) tensors each.

    a -> a_gen: A's points and where the network puts them in B's frame; b_gen -> b: B's points generated
    in A's frame and B's points. Inliers of both obey x_B = T_BA x_A.
    """

    a: torch.Tensor
    a_gen: torch.Tensor
    b: torch.Tensor
    b_gen: torch.Tensor

    def union(self) -> tuple[np.ndarray, np.ndarray]:
        """(src (2N, 3) in A's frame, dst (2N, 3) in B's frame) float64, dst_i ~ T_BA src_i for inliers."""
        src, dst = union_correspondences(self.a, self.a_gen, self.b, self.b_gen)
        return src[0].double().numpy(), dst[0].double().numpy()


@dataclass(frozen=True)
class RansacSettings:
    """Open3D RANSAC settings; the inlier distance is PDSAC's inlier_threshold."""

    ransac_n: int = 3  # correspondences per minimal sample (drawn with replacement by Open3D)
    max_iteration: int = 100_000  # its loop still walks every index after an early exit (a fixed cost)
    confidence: float = 0.999  # early exit once P(an all-inlier sample was drawn) reaches this


Solver = Callable[[Correspondences, PDSACConfig, int | None], np.ndarray]  # -> 4x4 T_BA, normalised units


def solve_pdsac(c: Correspondences, cfg: PDSACConfig, seed: int | None) -> np.ndarray:
    """The API's solver: `pdsac_bidirectional`, hypotheses drawn from a generator seeded like `Registrar`."""
    gen = torch.Generator().manual_seed(seed) if seed is not None else None
    with torch.no_grad():
        T, *_ = pdsac_bidirectional(c.a, c.a_gen, c.b, c.b_gen, cfg, gen)
    return T[0].double().numpy()


def solve_o3d_ransac(
    c: Correspondences, cfg: PDSACConfig, seed: int | None, settings: RansacSettings = RansacSettings(),
    refit: bool = False,
) -> np.ndarray:
    """Open3D correspondence RANSAC on the union (identity if it finds nothing); `refit`: PDSAC's refit after."""
    src, dst = c.union()
    index = np.arange(len(src), dtype=np.int32)
    corres = o3d.utility.Vector2iVector(np.column_stack([index, index]))
    if seed is not None:
        o3d.utility.random.seed(seed)  # Open3D's global generator; runs still differ slightly (Open3D #7475)
    result = reg.registration_ransac_based_on_correspondence(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst)),
        corres, cfg.inlier_threshold, reg.TransformationEstimationPointToPoint(False), settings.ransac_n, [],
        reg.RANSACConvergenceCriteria(settings.max_iteration, settings.confidence),
    )
    T = np.asarray(result.transformation).copy()
    if refit:
        T_t, _ = refit_on_inliers(torch.from_numpy(T)[None], torch.from_numpy(src)[None],
                                  torch.from_numpy(dst)[None], cfg.inlier_threshold)
        T = T_t[0].numpy()
    return T


def pose_solvers(settings: RansacSettings = RansacSettings()) -> dict[str, Solver]:
    """The compared solvers, in table order."""
    return {
        "pdsac": solve_pdsac,
        "o3d-ransac": partial(solve_o3d_ransac, settings=settings),
        "o3d-ransac+refit": partial(solve_o3d_ransac, settings=settings, refit=True),
    }


def generate(
    registrar: Registrar, source: np.ndarray, target: np.ndarray
) -> tuple[Correspondences, np.ndarray, float, float]:
    """One network pass on the pair as `Registrar.register` prepares it (no initial guess, one pass).

    Returns (correspondences, offset, scale, network seconds); x_normalised = (x - offset) / scale.
    """
    cfg = registrar.config
    src, _ = validate_cloud(source, "source", cfg.min_points)
    tgt, _ = validate_cloud(target, "target", cfg.min_points)
    rng = np.random.default_rng(cfg.seed)
    offset, scale = unit_box_normalization(src)
    n = registrar.num_points
    a = torch.from_numpy(((subsample(src, n, rng) - offset) / scale).astype(np.float32))[None]
    b = torch.from_numpy(((subsample(tgt, n, rng) - offset) / scale).astype(np.float32))[None]
    t0 = time.perf_counter()
    with torch.no_grad():
        out = registrar.model(a.to(cfg.device), b.to(cfg.device))
    seconds = time.perf_counter() - t0
    c = Correspondences(a, out.source_generated.cpu(), b, out.target_generated.cpu())
    return c, offset, scale, seconds


def pair_truth(item: dict[str, Any], index: int, options: BenchOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(T_gt float64, source CD subset, target CD subset, CD at the true pose): the CD points of
    `suites.run_dataset` for this pair, so that the CDs compare across tables."""
    src, tgt = item["source"].astype(np.float64), item["target"].astype(np.float64)
    T_gt = np.asarray(item["transform"], dtype=np.float64)
    rng = np.random.default_rng((options.seed, index))
    src_cd, tgt_cd = _cd_subset(src, options.cd_points, rng), _cd_subset(tgt, options.cd_points, rng)
    return T_gt, src_cd, tgt_cd, chamfer_distance(apply_transform(T_gt, src_cd), tgt_cd)


def generation_errors(c: Correspondences, T_gt: np.ndarray, offset: np.ndarray, scale: float) -> tuple[float, float]:
    """(Chamfer distance, mean squared point error) between A_g and T_gt A, dataset units."""
    a = c.a[0].double().numpy() * scale + offset
    a_gen = c.a_gen[0].double().numpy() * scale + offset
    truth = apply_transform(T_gt, a)
    return chamfer_distance(a_gen, truth), float(np.mean(np.sum((a_gen - truth) ** 2, axis=1)))


def run_backbone_dataset(
    spec: DatasetSpec, pairs: Any, indices: Sequence[int], registrars: dict[str, Registrar],
    options: BenchOptions, progress: tqdm | None = None,
) -> tuple[list[dict[str, Any]], dict[str, list[float]]]:
    """Records (one per pair and backbone: dataset, pair, method = backbone name, re_deg, te, cd, seconds,
    network_seconds, success, gen_cd, gen_mse, or error) and the per-pair list cd_floor."""
    first = pairs[indices[0]]
    for registrar in registrars.values():  # first-call costs stay out of the timings
        warm, *_ = generate(registrar, first["source"], first["target"])
        solve_pdsac(warm, registrar.config.pdsac, registrar.config.seed)
    records: list[dict[str, Any]] = []
    floors: list[float] = []
    for i in indices:
        item = pairs[i]
        T_gt, src_cd, tgt_cd, floor = pair_truth(item, i, options)
        floors.append(floor)
        for name, registrar in registrars.items():
            rec: dict[str, Any] = {"dataset": spec.name, "pair": int(i), "method": name}
            try:
                c, offset, scale, net_seconds = generate(registrar, item["source"], item["target"])
                t0 = time.perf_counter()
                T_n = solve_pdsac(c, registrar.config.pdsac, registrar.config.seed)
                seconds = net_seconds + time.perf_counter() - t0
                re, te, cd = evaluate(denormalize_transform(T_n, offset, scale), T_gt, src_cd, tgt_cd)
                gen_cd, gen_mse = generation_errors(c, T_gt, offset, scale)
                rec.update(re_deg=re, te=te, cd=cd, seconds=seconds, network_seconds=net_seconds,
                           success=spec.success(re, te), gen_cd=gen_cd, gen_mse=gen_mse)
            except Exception as exc:  # noqa: BLE001 - one model failing on one pair is a failure, not a crash
                rec.update(failure_fields(exc))
            records.append(rec)
        if progress is not None:
            progress.update(1)
    return records, {"cd_floor": floors}


def union_inlier_ratio(T_n: np.ndarray, c: Correspondences, threshold: float) -> float:
    """Share of the 2N correspondences with |T_n src - dst| < threshold (normalised units)."""
    parts = (x.double() for x in (c.a, c.a_gen, c.b, c.b_gen))
    return float(union_inlier_share(torch.from_numpy(T_n)[None], *parts, threshold)[0])


def run_pose_solver_dataset(
    spec: DatasetSpec, pairs: Any, indices: Sequence[int], registrar: Registrar, options: BenchOptions,
    solvers: dict[str, Solver], progress: tqdm | None = None,
) -> tuple[list[dict[str, Any]], dict[str, list[float]]]:
    """Records (one per pair and solver) and per-pair lists (cd_floor, gt_inlier_ratio, network_seconds).

    Record: dataset, pair, method (the solver), re_deg, te, cd, seconds (solver only), success,
    inlier_ratio (union correspondences within the inlier threshold of the estimate), error on failure.
    gt_inlier_ratio: the same share at the true pose (how good the generated correspondences are).
    """
    cfg = registrar.config
    warm, *_ = generate(registrar, pairs[indices[0]]["source"], pairs[indices[0]]["target"])
    for solve in solvers.values():  # first-call costs (allocations, thread pools) stay out of the timings
        solve(warm, cfg.pdsac, cfg.seed)
    records: list[dict[str, Any]] = []
    per_pair: dict[str, list[float]] = {"cd_floor": [], "gt_inlier_ratio": [], "network_seconds": []}
    for i in indices:
        item = pairs[i]
        T_gt, src_cd, tgt_cd, floor = pair_truth(item, i, options)
        per_pair["cd_floor"].append(floor)
        try:
            c, offset, scale, net_seconds = generate(registrar, item["source"], item["target"])
            T_gt_n = T_gt.copy()  # the true pose in normalised units (inverse of `denormalize_transform`)
            T_gt_n[:3, 3] = (T_gt[:3, 3] + T_gt[:3, :3] @ offset - offset) / scale
            gt_inliers = union_inlier_ratio(T_gt_n, c, cfg.pdsac.inlier_threshold)
        except Exception as exc:  # noqa: BLE001 - an unusable pair fails every solver, not the run
            failed, net_seconds, gt_inliers = f"{type(exc).__name__}: {exc}", float("nan"), float("nan")
        else:
            failed = None
        per_pair["gt_inlier_ratio"].append(gt_inliers)
        per_pair["network_seconds"].append(net_seconds)
        for name, solve in solvers.items():
            rec: dict[str, Any] = {"dataset": spec.name, "pair": int(i), "method": name}
            try:
                if failed:
                    raise RuntimeError(f"no correspondences: {failed}")
                t0 = time.perf_counter()
                T_n = solve(c, cfg.pdsac, cfg.seed)
                seconds = time.perf_counter() - t0
                re, te, cd = evaluate(denormalize_transform(T_n, offset, scale), T_gt, src_cd, tgt_cd)
                rec.update(re_deg=re, te=te, cd=cd, seconds=seconds, success=spec.success(re, te),
                           inlier_ratio=union_inlier_ratio(T_n, c, cfg.pdsac.inlier_threshold))
            except Exception as exc:  # noqa: BLE001 - one solver failing on one pair is a failure, not a crash
                rec.update(failure_fields(exc))
            records.append(rec)
        if progress is not None:
            progress.update(1)
    return records, per_pair


def pose_solver_description(cfg: RegistrationConfig, settings: RansacSettings, threads: int) -> str:
    p = cfg.pdsac
    return (
        "The GenReg network runs once per pair (inputs resampled to the model's N and normalised as in the API); "
        "every solver estimates the pose from the same generated correspondences {A_i -> A_g,i} and "
        "{B_g,i -> B_i} (2N in all). "
        f"`pdsac`: the API's `pdsac_bidirectional` ({p.num_hypotheses} hypotheses of {p.sample_size} "
        f"correspondences per direction, truncated-residual score, refit={p.refit}, seed {cfg.seed}). "
        "`o3d-ransac`: Open3D `registration_ransac_based_on_correspondence` on the 2N correspondences "
        f"(ransac_n {settings.ransac_n}, point-to-point, no checkers, at most {settings.max_iteration} "
        f"iterations, confidence {settings.confidence}; seeded, yet not bit-reproducible from run to run); it "
        "returns its best minimal-sample transform. "
        "`o3d-ransac+refit`: that transform refit by least squares on its inliers (PDSAC's refit). "
        f"Inlier distance {p.inlier_threshold} (unit box of the source) for all; `inliers`: mean share of the 2N "
        "correspondences within it of the estimate (`ground truth`: of the true pose). "
        f"Solver ms: solver wall time alone, median, {threads} thread(s); the network's time is not in it."
    )


def backbone_description(cfg: RegistrationConfig, backbones: dict[str, str], threads: int) -> str:
    p = cfg.pdsac
    return (
        "Each row is a GenReg object model whose per-point encoder is the named backbone, trained with the same "
        "recipe, data, seed and number of iterations (`scripts/ablation_backbone.sh`): `pointmixer` = PPF "
        "encoder + edge convolution + the paper's two mixer layers (the shipped architecture); `dgcnn` = the "
        "same without the mixer layers; `pointnet2` = PointNet++-style set abstraction (every point, then "
        "N/4 farthest-point centres) and feature propagation on the same point-pair features. "
        f"Checkpoints: {', '.join(f'`{n}` {c}' for n, c in backbones.items())}. "
        f"Registration as the API's `genreg` method: network, then PDSAC ({p.num_hypotheses} hypotheses, "
        f"seed {cfg.seed}). Generation: `gen CD` and `gen MSE` between A_g and T_gt A (the N network inputs). "
        f"ms: network + PDSAC, median, batch 1, {threads} thread(s)."
    )


def _load_registrars(checkpoints: dict[str, str], cfg: RegistrationConfig, what: str,
                     skipped: list[str], log: Callable[[str], None]) -> dict[str, Registrar]:
    """Registrars of the loadable checkpoints; each one that fails to load is skipped with a message."""
    registrars: dict[str, Registrar] = {}
    for name, checkpoint in checkpoints.items():
        try:
            registrars[name] = Registrar.from_checkpoint(checkpoint, cfg)
        except CheckpointError as exc:
            skipped.append(f"Ablation skipped {what} {name}: {exc}")
            log(skipped[-1])
    return registrars


def _dataset_info(spec: DatasetSpec, pairs: Any, indices: Sequence[int], checkpoint: str, num_points: int) -> dict[str, Any]:
    return {
        "title": spec.title, "kind": spec.kind, "units": spec.units, "checkpoint": checkpoint,
        "num_points": num_points, "success": asdict(spec.success), "pairs": len(indices),
        "available_pairs": len(pairs), "indices": list(indices), "points_per_cloud": len(pairs[indices[0]]["source"]),
    }


def run_ablations(
    suite: str | Suite,
    checkpoints: dict[str, str] | None = None,
    options: BenchOptions | None = None,
    names: Sequence[str] = (POSE_SOLVER,),
    datasets: Sequence[str] | None = None,
    max_pairs: int | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
    ransac: RansacSettings = RansacSettings(),
    backbones: dict[str, str] | None = None,
) -> BenchRun:
    """Run ablations ('pose-solver', 'backbone') on the suite's datasets; a `BenchRun` with `ablations` only.

    Section: name, title, description, column, order (row order), extras (table columns beyond the suites':
    record key, header, format, optional per-dataset ground-truth list), settings, datasets (per dataset:
    title, kind, units, checkpoint, num_points, success, pairs, available_pairs, indices, points_per_cloud
    and per-pair lists), records. The backbone ablation runs on object datasets only, with `backbones`
    (name -> checkpoint; default `DEFAULT_BACKBONES`).
    """
    unknown = sorted(set(names) - set(ABLATIONS))
    if unknown:
        raise ValueError(f"unknown ablations {unknown}; known: {list(ABLATIONS)}")
    suite_name, spec_suite, options = resolve_suite(suite, options)
    checkpoints = {**DEFAULT_CHECKPOINTS, **(checkpoints or {})}
    backbones = dict(backbones or DEFAULT_BACKBONES)
    load_start = os.getloadavg()[0]
    names_ds = [n for n in spec_suite.counts if datasets is None or n in datasets]
    plan = plan_pairs(spec_suite, names_ds, options, max_pairs)
    cfg = RegistrationConfig(seed=options.seed)
    skipped: list[str] = []
    sections: list[dict[str, Any]] = []
    if POSE_SOLVER in names:
        kinds = {kind: checkpoints[kind] for kind in sorted({spec.kind for spec, _, _ in plan})}
        registrars = _load_registrars(kinds, cfg, "pose-solver on", skipped, log)
        solvers = pose_solvers(ransac)
        section: dict[str, Any] = {
            "name": POSE_SOLVER, "title": POSE_SOLVER_TITLE, "column": "solver", "order": list(solvers),
            "extras": [{"key": "inlier_ratio", "header": "inliers", "format": "pct", "truth": "gt_inlier_ratio"}],
            "description": pose_solver_description(cfg, ransac, options.threads),
            "settings": {"pdsac": asdict(cfg.pdsac), "ransac": asdict(ransac), "seed": cfg.seed},
            "datasets": {}, "records": [],
        }
        runnable = [(s, p, ix) for s, p, ix in plan if s.kind in registrars]
        bar = tqdm(total=sum(len(ix) for _, _, ix in runnable), unit="pair", disable=not progress)
        for spec, pairs, indices in runnable:
            bar.set_description(f"{POSE_SOLVER} {spec.name}")
            registrar = registrars[spec.kind]
            records, per_pair = run_pose_solver_dataset(spec, pairs, indices, registrar, options, solvers, bar)
            section["records"] += records
            section["datasets"][spec.name] = {
                **_dataset_info(spec, pairs, indices, checkpoints[spec.kind], registrar.num_points), **per_pair}
        bar.close()
        sections.append(section)
    if BACKBONE in names:
        registrars = _load_registrars(backbones, cfg, "backbone", skipped, log)
        section = {
            "name": BACKBONE, "title": BACKBONE_TITLE, "column": "backbone", "order": list(registrars),
            "extras": [{"key": "gen_cd", "header": "gen CD", "format": "f4"},
                       {"key": "gen_mse", "header": "gen MSE", "format": "f5"}],
            "description": backbone_description(cfg, backbones, options.threads),
            "settings": {"pdsac": asdict(cfg.pdsac), "seed": cfg.seed, "backbones": backbones},
            "datasets": {}, "records": [],
        }
        runnable = [(s, p, ix) for s, p, ix in plan if s.kind == OBJECT] if registrars else []
        bar = tqdm(total=sum(len(ix) for _, _, ix in runnable), unit="pair", disable=not progress)
        for spec, pairs, indices in runnable:
            bar.set_description(f"{BACKBONE} {spec.name}")
            records, per_pair = run_backbone_dataset(spec, pairs, indices, registrars, options, bar)
            section["records"] += records
            num_points = next(iter(registrars.values())).num_points
            section["datasets"][spec.name] = {
                **_dataset_info(spec, pairs, indices, "see the rows", num_points), **per_pair}
        bar.close()
        sections.append(section)
    meta = run_meta(suite_name, options, [], checkpoints, load_start)
    meta["ablations"] = list(names)
    return BenchRun(meta, {}, [], [], skipped, sections)
