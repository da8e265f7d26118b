"""The ablations: the pose solver (PDSAC against Open3D's RANSAC on the same generated
correspondences) and the backbone (the shipped PointMixer and DGCNN object models, optionally the paper's
own generator).

Both run the network as the API does: each pair is prepared by `Registrar.prepare` (`prepare_pair`
with the registrar's settings: source and target resampled to the model's N with the config's seed,
one similarity from the source's bounding box), then `Registrar.estimate` runs network + PDSAC on it
with PDSAC's generator seeded as `Registrar.register` seeds it (`generate`). Its estimate is the suite's
`genreg` method; its generated clouds are the correspondences the pose solvers share.

Backbone (`run_backbone_dataset`): each named checkpoint registers every pair through `generate`;
records hold RE, TE, CD and success as in the suites, `seconds` = network + PDSAC, `network_seconds`, and
the generation quality of the paper's ablation tables: `gen_cd`, the Chamfer distance, and `gen_mse`, the
mean squared point error |A_g,i - T_gt A_i|^2, between the generated A_g and the truly moved source
T_gt A (the N network inputs, dataset units).

Pose solver: every solver estimates T_BA (4x4, column vectors, target_from_source: b ~ R a + t) in
normalised units from the union of the correspondences {A_i -> A_g,i} and {B_g,i -> B_i}, which all obey
B-frame = T_BA A-frame (see `pdsac`); solvers never run the network:
- `pdsac`: `pdsac_bidirectional` with the RegistrationConfig's settings (m hypotheses of k points per
  direction, truncated-residual score on the union, least-squares refit on the union's inliers), from a
  generator seeded like the API's, so that it reproduces `Registrar.estimate`;
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

from genreg_bench.datasets import (
    OBJECT,
    BenchOptions,
    DatasetSpec,
    PairTruth,
    Suite,
    pair_truth,
    plan_suite,
)
from genreg_bench.methods import DEFAULT_CHECKPOINTS, MethodOutput, load_each
from genreg_bench.runner import (
    BenchRun,
    dataset_info,
    failure_fields,
    run_dataset,
    run_meta,
    scored_fields,
)
from genreg_core.config import ModelConfig, PDSACConfig, RegistrationConfig
from genreg_core.geometry import apply_transform
from genreg_core.metrics import chamfer_distance
from genreg_core.pdsac import (
    pdsac_bidirectional,
    refit_on_inliers,
    seeded_generator,
    union_correspondences,
    union_inlier_share,
)
from genreg_core.prepare import PreparedPair
from genreg_core.registration import Registrar

reg = o3d.pipelines.registration

POSE_SOLVER = "pose-solver"
POSE_SOLVER_TITLE = "Ablation: pose solver (same generated correspondences)"
BACKBONE = "backbone"
BACKBONE_TITLE = "Ablation: backbone"
ABLATIONS = (POSE_SOLVER, BACKBONE)
# The shipped object models; `scripts/ablation_backbone.sh` passes same-budget retrainings instead, and a
# checkpoint of the paper's generator (ModelConfig.architecture "paper") can be added as a "paper" row.
DEFAULT_BACKBONES = {"pointmixer": "modelnet40", "dgcnn": "modelnet40_dgcnn"}


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
class Generated:
    """One pair through `Registrar.estimate`: its correspondences, the prepared pair (the similarity back to
    dataset units), the API's normalised estimate T_BA (4x4 float64), and the wall times of the network and
    of network + PDSAC."""

    correspondences: Correspondences
    prepared: PreparedPair
    transform_n: np.ndarray
    network_seconds: float
    seconds: float


@dataclass(frozen=True)
class RansacSettings:
    """Open3D RANSAC settings; the inlier distance is PDSAC's inlier_threshold."""

    ransac_n: int = 3  # correspondences per minimal sample (drawn with replacement by Open3D)
    max_iteration: int = 100_000  # its loop still walks every index after an early exit (a fixed cost)
    confidence: float = 0.999  # early exit once P(an all-inlier sample was drawn) reaches this


Solver = Callable[[Correspondences, PDSACConfig, int | None], np.ndarray]  # -> 4x4 T_BA, normalised units


def solve_pdsac(c: Correspondences, cfg: PDSACConfig, seed: int | None) -> np.ndarray:
    """The API's solver: `pdsac_bidirectional`, hypotheses drawn from a generator seeded like `Registrar`."""
    with torch.no_grad():
        T, *_ = pdsac_bidirectional(c.a, c.a_gen, c.b, c.b_gen, cfg, seeded_generator(seed))
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
        corres, cfg.tau, reg.TransformationEstimationPointToPoint(False), settings.ransac_n, [],
        reg.RANSACConvergenceCriteria(settings.max_iteration, settings.confidence),
    )
    T = np.asarray(result.transformation).copy()
    if refit:
        T_t, _ = refit_on_inliers(torch.from_numpy(T)[None], torch.from_numpy(src)[None],
                                  torch.from_numpy(dst)[None], cfg.tau)
        T = T_t[0].numpy()
    return T


def pose_solvers(settings: RansacSettings = RansacSettings()) -> dict[str, Solver]:
    """The compared solvers, in table order."""
    return {
        "pdsac": solve_pdsac,
        "o3d-ransac": partial(solve_o3d_ransac, settings=settings),
        "o3d-ransac+refit": partial(solve_o3d_ransac, settings=settings, refit=True),
    }


def generate(registrar: Registrar, source: np.ndarray, target: np.ndarray) -> Generated:
    """The pair prepared as `Registrar.register` prepares it (no initial guess), then `Registrar.estimate`."""
    p = registrar.prepare(source, target)
    device = registrar.config.device
    a, b = torch.from_numpy(p.a)[None].to(device), torch.from_numpy(p.b)[None].to(device)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    with torch.no_grad():
        est = registrar.estimate(a, b, seeded_generator(registrar.config.seed), timings)
    seconds = time.perf_counter() - t0
    c = Correspondences(a.cpu(), est.source_generated.cpu(), b.cpu(), est.target_generated.cpu())
    return Generated(c, p, est.transform[0].double().cpu().numpy(), timings["network"], seconds)


def generation_errors(
    c: Correspondences, T_gt: np.ndarray, to_input_units: Callable[[np.ndarray], np.ndarray]
) -> tuple[float, float]:
    """(Chamfer distance, mean squared point error) between A_g and T_gt A, dataset units
    (`to_input_units`: normalised points to dataset units, e.g. `PreparedPair.points_to_input_units`)."""
    a = to_input_units(c.a[0].double().numpy())
    a_gen = to_input_units(c.a_gen[0].double().numpy())
    truth = apply_transform(T_gt, a)
    return chamfer_distance(a_gen, truth), float(np.mean(np.sum((a_gen - truth) ** 2, axis=1)))


def backbone_method(registrar: Registrar) -> Callable[[np.ndarray, np.ndarray], MethodOutput]:
    """A backbone row as a benchmark method: `generate`, its estimate in dataset units (details: the
    `Generated`, for the generation errors)."""
    def run(source: np.ndarray, target: np.ndarray) -> MethodOutput:
        g = generate(registrar, source, target)
        return MethodOutput(g.prepared.to_input_units(g.transform_n), g.seconds,
                            {"network_seconds": g.network_seconds}, details=g)

    return run


def generation_fields(out: MethodOutput, truth: PairTruth) -> dict[str, Any]:
    g: Generated = out.details
    gen_cd, gen_mse = generation_errors(g.correspondences, truth.transform, g.prepared.points_to_input_units)
    return {"gen_cd": gen_cd, "gen_mse": gen_mse}


def run_backbone_dataset(
    spec: DatasetSpec, pairs: Any, indices: Sequence[int], registrars: dict[str, Registrar],
    options: BenchOptions, progress: tqdm | None = None,
) -> tuple[list[dict[str, Any]], dict[str, list[float]]]:
    """Records (one per pair and backbone: dataset, pair, method = backbone name, re_deg, te, cd, seconds,
    success, network_seconds, gen_cd, gen_mse, or error) and the per-pair list cd_floor."""
    methods = {name: backbone_method(r) for name, r in registrars.items()}
    first = pairs[indices[0]]
    for method in methods.values():  # first-call costs stay out of the timings
        method(first["source"], first["target"])
    records, floors, _ = run_dataset(spec, pairs, indices, methods, options, progress, measure=generation_fields)
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
    warm = generate(registrar, pairs[indices[0]]["source"], pairs[indices[0]]["target"]).correspondences
    for solve in solvers.values():  # first-call costs (allocations, thread pools) stay out of the timings
        solve(warm, cfg.pdsac, cfg.seed)
    threshold = cfg.pdsac.tau
    records: list[dict[str, Any]] = []
    per_pair: dict[str, list[float]] = {"cd_floor": [], "gt_inlier_ratio": [], "network_seconds": []}
    for i in indices:
        item = pairs[i]
        truth = pair_truth(item, i, options)
        per_pair["cd_floor"].append(truth.cd_floor)
        try:
            g = generate(registrar, item["source"], item["target"])
            net_seconds = g.network_seconds
            gt_inliers = union_inlier_ratio(g.prepared.to_normalized(truth.transform), g.correspondences,
                                            threshold)
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
                T_n = solve(g.correspondences, cfg.pdsac, cfg.seed)
                seconds = time.perf_counter() - t0
                rec.update(scored_fields(spec, truth, g.prepared.to_input_units(T_n), seconds),
                           inlier_ratio=union_inlier_ratio(T_n, g.correspondences, threshold))
            except Exception as exc:  # noqa: BLE001 - one solver failing on one pair is a failure, not a crash
                rec.update(failure_fields(exc))
            records.append(rec)
        if progress is not None:
            progress.update(1)
    return records, per_pair


def pose_solver_description(cfg: RegistrationConfig, settings: RansacSettings, threads: int) -> str:
    p = cfg.pdsac
    return (
        "The GenReg network runs once per pair (inputs prepared as in the API, `prepare_pair`); "
        "every solver estimates the pose from the same generated correspondences {A_i -> A_g,i} and "
        "{B_g,i -> B_i} (2N in all). "
        f"`pdsac`: the API's `pdsac_bidirectional` ({p.num_hypotheses} hypotheses of {p.sample_size} "
        f"correspondences per direction, truncated-residual score, refit={p.refit}, seed {cfg.seed}). "
        "`o3d-ransac`: Open3D `registration_ransac_based_on_correspondence` on the 2N correspondences "
        f"(ransac_n {settings.ransac_n}, point-to-point, no checkers, at most {settings.max_iteration} "
        f"iterations, confidence {settings.confidence}; seeded, yet not bit-reproducible from run to run); it "
        "returns its best minimal-sample transform. "
        "`o3d-ransac+refit`: that transform refit by least squares on its inliers (PDSAC's refit). "
        f"Inlier distance {p.tau} (unit box of the source) for all; `inliers`: mean share of the 2N "
        "correspondences within it of the estimate (`ground truth`: of the true pose). "
        f"Solver ms: solver wall time alone, median, {threads} thread(s); the network's time is not in it."
    )


def describe_model(cfg: ModelConfig) -> str:
    """What a backbone row's network is, from its checkpoint's ModelConfig."""
    if cfg.architecture == "paper":
        return ("the paper's generator (T-Net, xyz GCNN, mixer layers, global feature interaction, decoder; "
                "`genreg_core.model.paper`)")
    if cfg.backbone == "dgcnn":
        return "point-pair-feature encoder + edge convolution + a linear layer, then the soft pointer"
    return "point-pair-feature encoder + edge convolution + the paper's two mixer layers, then the soft pointer"


def backbone_description(cfg: RegistrationConfig, models: dict[str, ModelConfig], backbones: dict[str, str],
                         threads: int) -> str:
    p = cfg.pdsac
    rows = "; ".join(f"`{name}` ({backbones[name]}): {describe_model(m)}" for name, m in models.items())
    return (
        f"Each row is a GenReg object model: {rows}. By default the rows are the shipped `modelnet40` and "
        "`modelnet40_dgcnn` models, each with its own training run (MODEL_CARD.md); "
        "`scripts/ablation_backbone.sh` retrains pointmixer and dgcnn with the same recipe, data, seed and "
        "number of iterations and compares those. "
        f"Registration as the API's `genreg` method: `Registrar.estimate`, network then PDSAC "
        f"({p.num_hypotheses} hypotheses, seed {cfg.seed}). Generation: `gen CD` and `gen MSE` between A_g and "
        f"T_gt A (the N network inputs). ms: network + PDSAC, median, batch 1, {threads} thread(s)."
    )


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
    suite_name, options, plan = plan_suite(suite, options, datasets, max_pairs)
    checkpoints = {**DEFAULT_CHECKPOINTS, **(checkpoints or {})}
    backbones = dict(backbones or DEFAULT_BACKBONES)
    load_start = os.getloadavg()[0]
    cfg = RegistrationConfig(seed=options.seed)

    def load(checkpoint: str) -> Registrar:
        return Registrar.from_checkpoint(checkpoint, cfg)

    skipped: list[str] = []
    sections: list[dict[str, Any]] = []
    if POSE_SOLVER in names:
        kinds = {kind: checkpoints[kind] for kind in sorted({spec.kind for spec, _, _ in plan})}
        registrars = load_each(kinds, load, "Ablation skipped pose-solver on {name}: {error}", skipped, log)
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
            section["datasets"][spec.name] = dataset_info(spec, pairs, indices, checkpoints[spec.kind],
                                                          num_points=registrar.num_points, **per_pair)
        bar.close()
        sections.append(section)
    if BACKBONE in names:
        registrars = load_each(backbones, load, "Ablation skipped backbone {name}: {error}", skipped, log)
        models = {name: r.model.config for name, r in registrars.items()}
        section = {
            "name": BACKBONE, "title": BACKBONE_TITLE, "column": "backbone", "order": list(registrars),
            "extras": [{"key": "gen_cd", "header": "gen CD", "format": "f4"},
                       {"key": "gen_mse", "header": "gen MSE", "format": "f5"}],
            "description": backbone_description(cfg, models, backbones, options.threads),
            "settings": {"pdsac": asdict(cfg.pdsac), "seed": cfg.seed, "backbones": backbones,
                         "models": {name: {"architecture": m.architecture, "backbone": m.backbone}
                                    for name, m in models.items()}},
            "datasets": {}, "records": [],
        }
        runnable = [(s, p, ix) for s, p, ix in plan if s.kind == OBJECT] if registrars else []
        bar = tqdm(total=sum(len(ix) for _, _, ix in runnable), unit="pair", disable=not progress)
        for spec, pairs, indices in runnable:
            bar.set_description(f"{BACKBONE} {spec.name}")
            records, per_pair = run_backbone_dataset(spec, pairs, indices, registrars, options, bar)
            section["records"] += records
            num_points = next(iter(registrars.values())).num_points
            section["datasets"][spec.name] = dataset_info(spec, pairs, indices, "see the rows",
                                                          num_points=num_points, **per_pair)
        bar.close()
        sections.append(section)
    meta = run_meta(suite_name, options, [], checkpoints, load_start)
    meta["ablations"] = list(names)
    return BenchRun(meta, {}, [], [], skipped, sections)
