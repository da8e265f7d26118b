"""Benchmark suites: the paper's datasets, the methods compared on them, and the run loop.

A run registers the same selected pairs of every dataset with every method, in one process with one
thread setting, and records per pair and method:
- RE: rotation error in degrees (angle of R_est R_gt^T); TE: |t_est - t_gt| in the dataset's units;
- CD: Chamfer distance (metrics.chamfer_distance) between the moved source and the target, on at most
  `cd_points` random points per cloud (the same points for every method); the CD at the true pose is
  stored per pair as the floor;
- seconds: wall time of one batch-1 registration including each method's own preprocessing;
- success: RE and TE below the dataset's thresholds (`Success`);
- GenReg only: confidence, fitness, inlier ratio and stage timings of `RegistrationResult`.
Transforms are 4x4 target_from_source (x_t = R x_s + t). GenReg methods load one checkpoint per dataset
kind ("object": ModelNet40, "scene": 7-Scenes and SUN3D); a missing checkpoint skips them with a message.
Ablations (issue 5) are separate sections of a run (`BenchRun.ablations`, module `ablation`); they reuse
the pair plan (`plan_pairs`), `evaluate` and `report.summarize`.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache
from typing import Any

import numpy as np
import torch
from torch.utils.data import ConcatDataset
from tqdm import tqdm

from genreg_core.bench.baselines import BASELINES, BaselineFn, BaselineParams, identity
from genreg_core.config import RefineConfig, RegistrationConfig
from genreg_core.data import (
    REDKITCHEN_VAL_FRAMES,
    FMRPairs,
    FramePairs,
    ModelNetPairs,
    RGBDSequence,
    load_modelnet40,
)
from genreg_core.errors import CheckpointError
from genreg_core.geometry import apply_transform, normalize_pair
from genreg_core.metrics import chamfer_distance, transform_errors
from genreg_core.pdsac import register_batch
from genreg_core.registration import Registrar, subsample

OBJECT, SCENE = "object", "scene"
DEFAULT_CHECKPOINTS = {OBJECT: "modelnet40", SCENE: "7scenes"}
GENREG_METHODS = ("genreg", "genreg+icp")
REFERENCE_METHODS = ("identity",)
ALL_METHODS = (*REFERENCE_METHODS, *GENREG_METHODS, *BASELINES)


@dataclass(frozen=True)
class Success:
    """A registration succeeds when RE < max_re_deg (degrees) and TE < max_te (dataset units)."""

    max_re_deg: float
    max_te: float

    def __call__(self, re_deg: float, te: float) -> bool:
        return bool(np.isfinite(re_deg) and re_deg < self.max_re_deg and te < self.max_te)


UNIT_BOX_SUCCESS = Success(5.0, 0.1)  # unit-box units: a tenth of the object's size
# Metres, real frame pairs. Frame motions are small (identity: ~0.4 deg at gap 1, ~4 deg at gap 10), so RE
# decides; TE is measured at the camera origin and carries a lever arm (0.5 deg at 3 m depth ~ 2.6 cm).
METRIC_SUCCESS = Success(2.0, 0.1)


@dataclass(frozen=True)
class BenchOptions:
    """Pair generation and measurement settings shared by every dataset of a run."""

    object_points: int = 512  # N per ModelNet40 cloud (independent subsets of the 1024 points)
    fmr_points: int = 1024  # N per FMR-style cloud (two independent subsets of one frame)
    frame_stride: int = 1  # real frame pairs: every stride-th pixel (1: full resolution, ~300k points)
    seed: int = 0  # pair draws, GenReg sampling and CD subsets
    cd_points: int = 4096  # CD on at most this many random points per cloud
    threads: int = 2  # reported, and small_gicp's worker count
    throughput_batch: int = 16  # batched GenReg throughput: pairs per forward pass
    data_root: str | None = None  # None: GENREG_DATA or ../shared/data


@dataclass(frozen=True)
class DatasetSpec:
    """One table: which pairs, which GenReg checkpoint kind, units, baseline settings, success rule."""

    name: str
    title: str
    kind: str  # OBJECT or SCENE: the checkpoint GenReg uses here
    metric: bool  # True: metres and metric baseline settings; False: unit box
    build: Callable[[BenchOptions], Any]  # -> indexable set of pair dicts (source, target, transform)

    @property
    def units(self) -> str:
        return "m" if self.metric else "unit box"

    @property
    def success(self) -> Success:
        return METRIC_SUCCESS if self.metric else UNIT_BOX_SUCCESS

    def baseline_params(self, threads: int) -> BaselineParams:
        return BaselineParams.metric_scene(threads) if self.metric else BaselineParams.unit_box(threads)


@lru_cache(maxsize=4)
def _shapes(categories: str, root: str | None) -> Any:
    return load_modelnet40("test", categories, root)


def _modelnet(categories: str, variant: str) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        return ModelNetPairs(_shapes(categories, o.data_root), o.object_points, variant, seed=o.seed)

    return build


def _frames(names: Sequence[str], gap: int, frames: Sequence[int] | None = None) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        sets = [FramePairs(RGBDSequence.open(n, o.data_root), gap, frames, stride=o.frame_stride) for n in names]
        return sets[0] if len(sets) == 1 else ConcatDataset(sets)

    return build


def _fmr(o: BenchOptions) -> Any:
    return FMRPairs(RGBDSequence.redkitchen(o.data_root), REDKITCHEN_VAL_FRAMES, o.fmr_points, seed=o.seed)


def _dataset_specs() -> dict[str, DatasetSpec]:
    specs = []
    for cats, label in (("seen", "seen categories (test split)"), ("unseen", "unseen categories")):
        for variant in ("clean", "noise", "partial"):
            specs.append(DatasetSpec(
                f"modelnet-{cats}-{variant}", f"ModelNet40 {label}, {variant}", OBJECT, False,
                _modelnet(cats, variant),
            ))
    val = REDKITCHEN_VAL_FRAMES
    stairs = [f"stairs-{k}" for k in range(1, 5)]
    specs += [
        DatasetSpec("redkitchen-fmr", "7-Scenes redkitchen validation, FMR-style pairs", SCENE, False, _fmr),
        DatasetSpec("redkitchen-gap1", "7-Scenes redkitchen validation, frame pairs gap 1", SCENE, True,
                    _frames(["redkitchen"], 1, val)),
        DatasetSpec("redkitchen-gap10", "7-Scenes redkitchen validation, frame pairs gap 10", SCENE, True,
                    _frames(["redkitchen"], 10, val)),
        DatasetSpec("stairs-gap1", "Unseen scene 7-Scenes stairs, gap 1", SCENE, True, _frames(stairs, 1)),
        DatasetSpec("stairs-gap2", "Unseen scene 7-Scenes stairs, gap 2", SCENE, True, _frames(stairs, 2)),
        DatasetSpec("sun3d-gap5", "Unseen scene SUN3D, gap 5", SCENE, True, _frames(["sun3d-1", "sun3d-2"], 5)),
    ]
    return {s.name: s for s in specs}


DATASETS: dict[str, DatasetSpec] = _dataset_specs()


@dataclass(frozen=True)
class Suite:
    """Pairs per dataset (None: all of them, evenly spread picks otherwise) and option overrides."""

    counts: dict[str, int | None]
    options: dict[str, Any] = field(default_factory=dict)


_MODELNET = [n for n in DATASETS if n.startswith("modelnet")]
SUITES: dict[str, Suite] = {
    # A few pairs end to end (CI): quarter-resolution frames keep it to seconds.
    "smoke": Suite({"modelnet-unseen-clean": 3, "modelnet-seen-partial": 2, "redkitchen-fmr": 2,
                    "redkitchen-gap10": 1}, {"frame_stride": 4}),
    # < 10 minutes on 2 cores.
    "quick": Suite({**{n: 25 for n in _MODELNET}, "redkitchen-fmr": 25, "redkitchen-gap1": 8,
                    "redkitchen-gap10": 8, "stairs-gap1": None, "stairs-gap2": None, "sun3d-gap5": 8}),
    # < 60 minutes on 2 cores.
    "full": Suite({**{n: 200 for n in _MODELNET}, "redkitchen-fmr": 200, "redkitchen-gap1": 66,
                   "redkitchen-gap10": 64, "stairs-gap1": None, "stairs-gap2": None, "sun3d-gap5": 45}),
}


def select_indices(total: int, count: int | None) -> list[int]:
    """All indices, or `count` evenly spread ones (first and last included): spans categories/frames."""
    if count is None or count >= total:
        return list(range(total))
    return sorted({round(x) for x in np.linspace(0, total - 1, count)})


def failure_fields(exc: Exception) -> dict[str, Any]:
    """Record fields of a registration that raised: NaN figures, no success, the error named."""
    nan = float("nan")
    return {"re_deg": nan, "te": nan, "cd": nan, "seconds": nan, "success": False,
            "error": f"{type(exc).__name__}: {exc}"}


@dataclass
class MethodOutput:
    """transformation: 4x4 target_from_source; seconds: wall time; extra: JSON-ready method details."""

    transformation: np.ndarray
    seconds: float
    extra: dict[str, Any] = field(default_factory=dict)


Method = Callable[[np.ndarray, np.ndarray], MethodOutput]


def baseline_method(fn: BaselineFn, params: BaselineParams) -> Method:
    def run(source: np.ndarray, target: np.ndarray) -> MethodOutput:
        T, seconds = fn(source, target, params)
        return MethodOutput(T, seconds)

    return run


def genreg_method(registrar: Registrar) -> Method:
    def run(source: np.ndarray, target: np.ndarray) -> MethodOutput:
        t0 = time.perf_counter()
        result = registrar.register(source, target)
        seconds = time.perf_counter() - t0
        extra = {
            "confidence": result.confidence, "fitness": result.fitness, "inlier_ratio": result.inlier_ratio,
            "timings": {k: float(v) for k, v in result.timings.items()},
        }
        return MethodOutput(result.transformation, seconds, extra)

    return run


def load_genreg(checkpoint: str, seed: int) -> dict[str, Registrar]:
    """'genreg' (network + PDSAC) and 'genreg+icp' (the API's point-to-point refinement, default guard) on
    one model."""
    plain = Registrar.from_checkpoint(checkpoint, RegistrationConfig(seed=seed))
    refine = RegistrationConfig(seed=seed, refine=RefineConfig(method="point_to_point"))
    return {"genreg": plain, "genreg+icp": Registrar(plain.model, refine)}


@dataclass
class BenchRun:
    """Everything a report needs; `records` holds one JSON-ready dict per (pair, method)."""

    meta: dict[str, Any]
    datasets: dict[str, dict[str, Any]]
    records: list[dict[str, Any]]
    throughput: list[dict[str, Any]]
    skipped: list[str]
    ablations: list[dict[str, Any]] = field(default_factory=list)  # JSON-ready sections (`ablation`)


def _cd_subset(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return points if len(points) <= n else points[rng.choice(len(points), n, replace=False)]


def evaluate(T: np.ndarray, T_gt: np.ndarray, src_cd: np.ndarray, tgt_cd: np.ndarray) -> tuple[float, float, float]:
    """(RE deg, TE, CD) of an estimate; NaN for a non-finite transform."""
    if not np.isfinite(T).all():
        return float("nan"), float("nan"), float("nan")
    re, te = transform_errors(T, T_gt)
    return re, te, chamfer_distance(apply_transform(T, src_cd), tgt_cd)


def run_dataset(
    spec: DatasetSpec, pairs: Any, indices: Sequence[int], methods: dict[str, Method], options: BenchOptions,
    progress: tqdm | None = None,
) -> tuple[list[dict[str, Any]], list[float]]:
    """Register pairs[i] for i in indices with every method; returns (records, CD floor per pair)."""
    records, floors = [], []
    success = spec.success
    for i in indices:
        item = pairs[i]
        src, tgt = item["source"].astype(np.float64), item["target"].astype(np.float64)
        T_gt = np.asarray(item["transform"], dtype=np.float64)
        rng = np.random.default_rng((options.seed, i))
        src_cd, tgt_cd = _cd_subset(src, options.cd_points, rng), _cd_subset(tgt, options.cd_points, rng)
        floors.append(chamfer_distance(apply_transform(T_gt, src_cd), tgt_cd))
        for name, method in methods.items():
            rec: dict[str, Any] = {"dataset": spec.name, "pair": int(i), "method": name}
            try:
                out = method(item["source"], item["target"])
                re, te, cd = evaluate(out.transformation, T_gt, src_cd, tgt_cd)
                rec.update(re_deg=re, te=te, cd=cd, seconds=out.seconds, success=success(re, te), **out.extra)
            except Exception as exc:  # noqa: BLE001 - one method failing on one pair is a failure, not a crash
                rec.update(failure_fields(exc))
            records.append(rec)
        if progress is not None:
            progress.update(1)
    return records, floors


def measure_throughput(
    registrar: Registrar, pairs: Any, indices: Sequence[int], batch: int, repeats: int = 3
) -> dict[str, Any]:
    """Network + PDSAC only (the API's own path, `pdsac.register_batch`), ms per pair: batch 1 vs `batch`.

    Inputs are prepared like the API (joint unit-box normalisation, resampling to the model's N) and
    cycled to fill the batch; the median of `repeats` runs is reported.
    """
    rng = np.random.default_rng(0)
    n = registrar.num_points
    clouds = []
    for k in range(batch):
        item = pairs[indices[k % len(indices)]]
        src_n, tgt_n, *_ = normalize_pair(item["source"].astype(np.float64), item["target"].astype(np.float64))
        clouds.append((subsample(src_n, n, rng), subsample(tgt_n, n, rng)))
    a = torch.from_numpy(np.stack([c[0] for c in clouds]))
    b = torch.from_numpy(np.stack([c[1] for c in clouds]))
    cfg = registrar.config

    def once(x: torch.Tensor, y: torch.Tensor) -> float:
        gen = torch.Generator().manual_seed(0)
        t0 = time.perf_counter()
        with torch.no_grad():
            register_batch(registrar.model, x, y, cfg.pdsac, cfg.passes, gen)
        return time.perf_counter() - t0

    once(a[:1], b[:1])  # warm-up, both shapes
    once(a, b)
    single = [once(a[k:k + 1], b[k:k + 1]) for k in range(min(batch, 8)) for _ in range(repeats)]
    batched = [once(a, b) / batch for _ in range(repeats)]
    return {"num_points": n, "batch": batch, "ms_batch1": 1e3 * float(np.median(single)),
            "ms_per_pair_batched": 1e3 * float(np.median(batched))}


def run_benchmark(
    suite: str | Suite,
    checkpoints: dict[str, str] | None = None,
    options: BenchOptions | None = None,
    methods: Sequence[str] | None = None,
    datasets: Sequence[str] | None = None,
    max_pairs: int | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> BenchRun:
    """Run a suite ('smoke', 'quick', 'full' or a `Suite`); `checkpoints` maps kind -> name or path.

    `methods` / `datasets` restrict the run; `max_pairs` caps the pairs per dataset.
    """
    suite_name, spec_suite, options = resolve_suite(suite, options)
    checkpoints = {**DEFAULT_CHECKPOINTS, **(checkpoints or {})}
    wanted = list(methods or ALL_METHODS)
    unknown = sorted(set(wanted) - set(ALL_METHODS))
    if unknown:
        raise ValueError(f"unknown methods {unknown}; known: {list(ALL_METHODS)}")
    names = [n for n in spec_suite.counts if datasets is None or n in datasets]

    load_start = os.getloadavg()
    skipped: list[str] = []
    genreg: dict[str, dict[str, Registrar]] = {}
    for kind in sorted({DATASETS[n].kind for n in names}):
        if not any(m in GENREG_METHODS for m in wanted):
            break
        try:
            genreg[kind] = load_genreg(checkpoints[kind], options.seed)
        except CheckpointError as exc:
            msg = f"GenReg skipped on {kind} datasets: {exc}"
            skipped.append(msg)
            log(msg)

    plan = plan_pairs(spec_suite, names, options, max_pairs)
    records, infos, throughput = [], {}, []
    warmed: set[tuple[str, str, bool]] = set()
    bar = tqdm(total=sum(len(p[2]) for p in plan), unit="pair", disable=not progress)
    for spec, pairs, indices in plan:
        bar.set_description(spec.name)
        params = spec.baseline_params(options.threads)
        table: dict[str, Method] = {}
        for m in wanted:
            if m == "identity":
                table[m] = baseline_method(identity, params)
            elif m in BASELINES:
                table[m] = baseline_method(BASELINES[m], params)
            elif spec.kind in genreg:
                table[m] = genreg_method(genreg[spec.kind][m])
        warm = pairs[indices[0]]
        for m, method in table.items():  # first-call costs (allocations, thread pools) stay out of the timings
            if (m, spec.kind, spec.metric) not in warmed:
                method(warm["source"], warm["target"])
                warmed.add((m, spec.kind, spec.metric))
        recs, floors = run_dataset(spec, pairs, indices, table, options, bar)
        records += recs
        sample = pairs[indices[0]]
        infos[spec.name] = {
            "title": spec.title, "kind": spec.kind, "units": spec.units, "checkpoint": checkpoints[spec.kind],
            "genreg": spec.kind in genreg, "success": asdict(spec.success), "pairs": len(indices),
            "available_pairs": len(pairs), "indices": list(indices), "cd_floor": floors,
            "points_per_cloud": len(sample["source"]), "baseline_params": asdict(params),
        }
    bar.close()

    for kind, regs in genreg.items():
        first = next(((s, p, ix) for s, p, ix in plan if s.kind == kind), None)
        if first is not None and "genreg" in wanted:
            spec, pairs, indices = first
            row = measure_throughput(regs["genreg"], pairs, indices, options.throughput_batch)
            throughput.append({"kind": kind, "checkpoint": checkpoints[kind], "dataset": spec.name, **row})

    meta = run_meta(suite_name, options, wanted, checkpoints, load_start[0])
    return BenchRun(meta, infos, records, throughput, skipped)


def resolve_suite(suite: str | Suite, options: BenchOptions | None) -> tuple[str, Suite, BenchOptions]:
    """(name, Suite, options with the suite's overrides) of a suite name or a custom `Suite`."""
    spec_suite = SUITES[suite] if isinstance(suite, str) else suite
    return (suite if isinstance(suite, str) else "custom", spec_suite,
            replace(options or BenchOptions(), **spec_suite.options))


def plan_pairs(
    suite: Suite, names: Sequence[str], options: BenchOptions, max_pairs: int | None
) -> list[tuple[DatasetSpec, Any, list[int]]]:
    """(spec, pair set, selected indices) per dataset name: the suite's count, capped by `max_pairs`."""
    plan = []
    for name in names:
        spec = DATASETS[name]
        pairs = spec.build(options)
        count = suite.counts[name]
        count = min(count, max_pairs) if count is not None and max_pairs else (count or max_pairs)
        plan.append((spec, pairs, select_indices(len(pairs), count)))
    return plan


def run_meta(
    suite_name: str, options: BenchOptions, methods: Sequence[str], checkpoints: dict[str, str], load_start: float
) -> dict[str, Any]:
    """The `BenchRun.meta` of a run: settings, threads, machine, date and the 1-minute load average."""
    return {
        "suite": suite_name, "options": asdict(options), "methods": list(methods), "checkpoints": checkpoints,
        "threads": thread_report(options.threads),
        "load_average": {"start": load_start, "end": os.getloadavg()[0]},  # 1-minute, other jobs included
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "torch": torch.__version__},
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def thread_report(threads: int) -> dict[str, Any]:
    """The thread settings in force (torch intra-op, OpenMP env for Open3D, small_gicp workers)."""
    return {
        "requested": threads, "torch": torch.get_num_threads(),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"), "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "small_gicp": threads,
    }
