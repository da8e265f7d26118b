"""Benchmark runner: registers the same selected pairs of every dataset with every method, and records it.

A run registers the pairs of `datasets.plan_pairs` with the `methods` tables, in one process with one
thread setting, and records per pair and method:
- RE: rotation error in degrees (angle of R_est R_gt^T); TE: |t_est - t_gt| in the dataset's units;
- CD: Chamfer distance (metrics.chamfer_distance) between the moved source and the target, on at most
  `cd_points` random points per cloud (the same points for every method, `datasets.pair_truth`); the CD
  at the true pose is stored per pair as the floor;
- seconds: wall time of one batch-1 registration including each method's own preprocessing;
- success: RE and TE below the dataset's thresholds (`datasets.Success`);
- overlap: the pair's overlap share at the true pose (`datasets.overlap_share`, the dataset frame's
  radius; also listed per pair in the dataset's entry); category: ModelNet40 pairs' category name;
- GenReg only: confidence, fitness, inlier ratio and stage timings of `RegistrationResult`.
Transforms are 4x4 target_from_source (x_t = R x_s + t). A missing GenReg checkpoint skips its methods
with a message. Ablations are separate sections of a run (`BenchRun.ablations`, module `ablation`); they
reuse the pair plan, `run_dataset` and `report.summarize`. `run_meta` records the machine and threads.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from genreg_bench.datasets import (
    SCENE,
    BenchOptions,
    DatasetSpec,
    PairTruth,
    Suite,
    pair_truth,
    plan_suite,
    resolve_suite,
)
from genreg_bench.methods import (
    ALL_METHODS,
    DEFAULT_CHECKPOINTS,
    DEFAULT_METHODS,
    GENREG_METHODS,
    TRUTH_METHODS,
    Method,
    MethodOutput,
    TruthMethod,
    load_each,
    load_genreg,
    measure_throughput,
    method_table,
)
from genreg_core.config import SCENE_REGISTRATION

Measure = Callable[[MethodOutput, PairTruth], dict[str, Any]]  # extra record fields from output and truth


@dataclass
class BenchRun:
    """Everything a report needs; `records` holds one JSON-ready dict per (pair, method)."""

    meta: dict[str, Any]
    datasets: dict[str, dict[str, Any]]
    records: list[dict[str, Any]]
    throughput: list[dict[str, Any]]
    skipped: list[str]
    ablations: list[dict[str, Any]] = field(default_factory=list)  # JSON-ready sections (`ablation`)


def failure_fields(exc: Exception) -> dict[str, Any]:
    """Record fields of a registration that raised: NaN figures, no success, the error named."""
    nan = float("nan")
    return {"re_deg": nan, "te": nan, "cd": nan, "seconds": nan, "success": False,
            "error": f"{type(exc).__name__}: {exc}"}


def scored_fields(spec: DatasetSpec, truth: PairTruth, T: Any, seconds: float) -> dict[str, Any]:
    """Record fields of one estimate: re_deg, te, cd, seconds, success."""
    re, te, cd = truth.errors(T)
    return {"re_deg": re, "te": te, "cd": cd, "seconds": seconds, "success": spec.success(re, te)}


def call(name: str, method: Method | TruthMethod, item: dict[str, Any]) -> MethodOutput:
    """One method on one pair: the `TRUTH_METHODS` are given its true pose as well."""
    if name in TRUTH_METHODS:
        return method(item["source"], item["target"], np.asarray(item["transform"], dtype=np.float64))
    return method(item["source"], item["target"])


def run_dataset(
    spec: DatasetSpec, pairs: Any, indices: Sequence[int], methods: dict[str, Method | TruthMethod],
    options: BenchOptions,
    progress: tqdm | None = None, measure: Measure | None = None,
) -> tuple[list[dict[str, Any]], list[float], list[float | None]]:
    """Register pairs[i] for i in indices with every method; returns (records, CD floor per pair, overlap
    share per pair).

    `measure` adds record fields from each output and the pair's truth (the ablations' generation errors).
    """
    records, floors, overlaps = [], [], []
    for i in indices:
        item = pairs[i]
        truth = pair_truth(item, i, options, spec.frame.overlap_radius)
        floors.append(truth.cd_floor)
        overlaps.append(truth.overlap)
        pair_fields = {"overlap": truth.overlap, **({"category": item["category"]} if "category" in item else {})}
        for name, method in methods.items():
            rec: dict[str, Any] = {"dataset": spec.name, "pair": int(i), "method": name, **pair_fields}
            try:
                out = call(name, method, item)
                rec.update(scored_fields(spec, truth, out.transformation, out.seconds), **out.extra)
                if measure is not None:
                    rec.update(measure(out, truth))
            except Exception as exc:  # noqa: BLE001 - one method failing on one pair is a failure, not a crash
                rec.update(failure_fields(exc))
            records.append(rec)
        if progress is not None:
            progress.update(1)
    return records, floors, overlaps


def dataset_info(spec: DatasetSpec, pairs: Any, indices: Sequence[int], checkpoint: str, **extra: Any) -> dict[str, Any]:
    """The `BenchRun.datasets` (or ablation section) entry of one dataset; `extra` adds fields."""
    return {
        "title": spec.title, "kind": spec.kind, "units": spec.units, "checkpoint": checkpoint,
        "success": asdict(spec.success), "pairs": len(indices), "available_pairs": len(pairs),
        "indices": list(indices), "points_per_cloud": len(pairs[indices[0]]["source"]),
        "overlap_radius": spec.frame.overlap_radius, **extra,
    }


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
    """Run a suite ('smoke', 'quick', 'full', 'partial' or a `Suite`); `checkpoints` maps kind -> name or path.

    `methods` (default: the suite's, else `DEFAULT_METHODS`) / `datasets` restrict the run; `max_pairs` caps
    the pairs per dataset. A method runs on the datasets it applies to (`DatasetSpec.applies`).
    """
    wanted = list(methods or resolve_suite(suite, options)[1].methods or DEFAULT_METHODS)
    unknown = sorted(set(wanted) - set(ALL_METHODS))
    if unknown:
        raise ValueError(f"unknown methods {unknown}; known: {list(ALL_METHODS)}")
    suite_name, options, plan = plan_suite(suite, options, datasets, max_pairs)
    checkpoints = {**DEFAULT_CHECKPOINTS, **(checkpoints or {})}

    load_start = os.getloadavg()
    skipped: list[str] = []
    genreg = {}
    if any(m in GENREG_METHODS for m in wanted):
        kinds = {kind: checkpoints[kind] for kind in sorted({spec.kind for spec, _, _ in plan})}
        for kind, checkpoint in kinds.items():  # scenes from the scene preset (config.SCENE_REGISTRATION)
            base = SCENE_REGISTRATION if kind == SCENE else None
            genreg.update(load_each({kind: checkpoint}, lambda c, b=base: load_genreg(c, options.seed, b),
                                    "GenReg skipped on {name} datasets: {error}", skipped, log))

    records, infos, throughput = [], {}, []
    warmed: set[tuple[str, str, str]] = set()
    bar = tqdm(total=sum(len(p[2]) for p in plan), unit="pair", disable=not progress)
    for spec, pairs, indices in plan:
        bar.set_description(spec.name)
        params = spec.baseline_params(options.threads)
        table = method_table([m for m in wanted if spec.applies(m)], params, genreg.get(spec.kind))
        warm = pairs[indices[0]]
        for m, method in table.items():  # first-call costs (allocations, thread pools) stay out of the timings
            if (m, spec.kind, spec.units) not in warmed:
                call(m, method, warm)
                warmed.add((m, spec.kind, spec.units))
        recs, floors, overlaps = run_dataset(spec, pairs, indices, table, options, bar)
        records += recs
        infos[spec.name] = dataset_info(spec, pairs, indices, checkpoints[spec.kind], genreg=spec.kind in genreg,
                                        cd_floor=floors, overlap=overlaps, methods=list(table),
                                        baseline_params=asdict(params))
    bar.close()

    for kind, regs in genreg.items():
        first = next(((s, p, ix) for s, p, ix in plan if s.kind == kind), None)
        if first is not None and "genreg" in wanted:
            spec, pairs, indices = first
            row = measure_throughput(regs["genreg"], pairs, indices, options.throughput_batch)
            throughput.append({"kind": kind, "checkpoint": checkpoints[kind], "dataset": spec.name, **row})

    meta = run_meta(suite_name, options, wanted, checkpoints, load_start[0])
    return BenchRun(meta, infos, records, throughput, skipped)


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
