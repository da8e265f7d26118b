"""Benchmark methods: GenReg (through the registration API) and the classical baselines as one callable.

A `Method` maps (source, target) arrays to a `MethodOutput`: the 4x4 target_from_source estimate, its wall
time (the method's own preprocessing included) and JSON-ready details (GenReg: confidence, fitness, inlier
ratio and stage timings of `RegistrationResult`). GenReg methods load one checkpoint per dataset kind
("object", "scene"): `genreg` (network + PDSAC), `genreg+icp`, `genreg+p2plane` and `genreg+gicp` (the API's
point-to-point / point-to-plane / GICP refinement with its guard, at the API's default refinement settings,
except the preset's own refinement: scenes' GICP is the node's, 20 iterations) and `genreg+p2plane+fallback`
(plus the opt-in FPFH + RANSAC fallback; reported apart from GenReg's own figures); `load_each` skips a checkpoint that does not load, with a
message. The reference `truth+gicp` (`TRUTH_METHODS`) is a `TruthMethod`: it is also given the true pose.
A suite runs its own methods (`datasets.Suite.methods`), `DEFAULT_METHODS` unless it names them.
`measure_throughput` times the network + PDSAC stage (`Registrar.estimate`) at batch 1 and batched.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

import numpy as np
import torch

from genreg_bench.baselines import BASELINES, BaselineFn, BaselineParams, identity, truth_gicp
from genreg_bench.datasets import OBJECT, SCENE
from genreg_core.config import (
    OBJECT_MODEL,
    SCENE_MODEL,
    FallbackConfig,
    RefineConfig,
    RegistrationConfig,
)
from genreg_core.errors import CheckpointError
from genreg_core.pdsac import seeded_generator
from genreg_core.registration import Registrar

DEFAULT_CHECKPOINTS = {OBJECT: OBJECT_MODEL, SCENE: SCENE_MODEL}
# genreg+p2plane+fallback: with the opt-in classical fallback (FPFH + RANSAC below confidence 0.3); reported
# apart, never counted as GenReg's own figures
GENREG_METHODS = ("genreg", "genreg+icp", "genreg+p2plane", "genreg+gicp", "genreg+p2plane+fallback")
# References, not methods: no registration; GICP started at the true pose (given the answer: on real frames,
# how often the clouds' geometry and the recorded pose disagree by more than the success rule allows)
REFERENCE_METHODS = ("identity", "truth+gicp")
TRUTH_METHODS = frozenset({"truth+gicp"})
ALL_METHODS = (*REFERENCE_METHODS, *GENREG_METHODS, *BASELINES)
# The smoke, quick and full suites' methods (the paper tables' comparison).
DEFAULT_METHODS = ("identity", "genreg", "genreg+icp", "icp-p2p", "icp-p2plane", "fpfh+fgr", "fpfh+ransac",
                   "fpfh+ransac+icp", "small_gicp")

Loaded = TypeVar("Loaded")


@dataclass
class MethodOutput:
    """transformation: 4x4 target_from_source; seconds: wall time; extra: JSON-ready method details;
    details: anything else a caller measures (not stored)."""

    transformation: np.ndarray
    seconds: float
    extra: dict[str, Any] = field(default_factory=dict)
    details: Any = None


Method = Callable[[np.ndarray, np.ndarray], MethodOutput]
TruthMethod = Callable[[np.ndarray, np.ndarray, np.ndarray], MethodOutput]  # also given the true pose


def baseline_method(fn: BaselineFn, params: BaselineParams) -> Method:
    def run(source: np.ndarray, target: np.ndarray) -> MethodOutput:
        T, seconds = fn(source, target, params)
        return MethodOutput(T, seconds)

    return run


def truth_method(params: BaselineParams) -> TruthMethod:
    def run(source: np.ndarray, target: np.ndarray, truth: np.ndarray) -> MethodOutput:
        T, seconds = truth_gicp(source, target, params, truth)
        return MethodOutput(T, seconds)

    return run


def genreg_method(registrar: Registrar) -> Method:
    def run(source: np.ndarray, target: np.ndarray) -> MethodOutput:
        t0 = time.perf_counter()
        result = registrar.register(source, target)
        seconds = time.perf_counter() - t0
        extra = {
            "confidence": result.confidence, "fitness": result.fitness,
            "tight_fitness": result.tight_fitness, "inlier_ratio": result.inlier_ratio, "passes": result.passes,
            "timings": {k: float(v) for k, v in result.timings.items()},
        }
        return MethodOutput(result.transformation, seconds, extra)

    return run


def load_genreg(checkpoint: str, seed: int, base: RegistrationConfig | None = None) -> dict[str, Registrar]:
    """'genreg' (network + PDSAC), 'genreg+icp', 'genreg+p2plane' and 'genreg+gicp' (the API's point-to-point,
    point-to-plane or GICP refinement with default refinement settings and guard; the refinement of `base`
    as it is) on one model with its confidence calibration, from the settings `base` (default: the API's;
    scenes: `config.SCENE_REGISTRATION`) with the run's seed."""
    base = replace(base or RegistrationConfig(), seed=seed)

    def config(method: str = "none", fallback: FallbackConfig | None = None) -> RegistrationConfig:
        refine = base.refine if base.refine.method == method else RefineConfig(method=method)  # the preset's own
        return replace(base, refine=refine, fallback=fallback or FallbackConfig())

    plain = Registrar.from_checkpoint(checkpoint, config())
    refined = {name: Registrar(plain.model, config(method), plain.calibration)
               for name, method in (("genreg+icp", "point_to_point"), ("genreg+p2plane", "point_to_plane"),
                                     ("genreg+gicp", "gicp"))}
    rescued = Registrar(plain.model, config("point_to_plane", FallbackConfig(method="fpfh_ransac")), plain.calibration)
    return {"genreg": plain, **refined, "genreg+p2plane+fallback": rescued}


def load_each(
    checkpoints: dict[str, str], load: Callable[[str], Loaded], message: str, skipped: list[str],
    log: Callable[[str], None],
) -> dict[str, Loaded]:
    """{name: load(checkpoint)} of the checkpoints that load; each CheckpointError is skipped with
    `message.format(name=name, error=exc)`, appended to `skipped` and logged."""
    loaded: dict[str, Loaded] = {}
    for name, checkpoint in checkpoints.items():
        try:
            loaded[name] = load(checkpoint)
        except CheckpointError as exc:
            skipped.append(message.format(name=name, error=exc))
            log(skipped[-1])
    return loaded


def method_table(
    wanted: Sequence[str], params: BaselineParams, genreg: dict[str, Registrar] | None
) -> dict[str, Method | TruthMethod]:
    """The wanted methods on one dataset, in order; GenReg methods only when its registrars loaded. The
    `TRUTH_METHODS` are called with the true pose as well."""
    table: dict[str, Method | TruthMethod] = {}
    for m in wanted:
        if m == "identity":
            table[m] = baseline_method(identity, params)
        elif m in TRUTH_METHODS:
            table[m] = truth_method(params)
        elif m in BASELINES:
            table[m] = baseline_method(BASELINES[m], params)
        elif genreg is not None:
            table[m] = genreg_method(genreg[m])
    return table


def measure_throughput(
    registrar: Registrar, pairs: Any, indices: Sequence[int], batch: int, repeats: int = 3
) -> dict[str, Any]:
    """Network + PDSAC only (`Registrar.estimate`, the API's own stage), ms per pair: batch 1 vs `batch`.

    Inputs are prepared like the API (`Registrar.prepare`) and cycled to fill the batch; the median of
    `repeats` runs is reported.
    """
    items = [pairs[indices[k % len(indices)]] for k in range(batch)]
    prepared = [registrar.prepare(item["source"], item["target"]) for item in items]
    device = registrar.config.device
    a = torch.from_numpy(np.stack([p.a for p in prepared])).to(device)
    b = torch.from_numpy(np.stack([p.b for p in prepared])).to(device)

    def once(x: torch.Tensor, y: torch.Tensor) -> float:
        gen = seeded_generator(0)
        t0 = time.perf_counter()
        with torch.no_grad():
            registrar.estimate(x, y, gen)
        return time.perf_counter() - t0

    once(a[:1], b[:1])  # warm-up, both shapes
    once(a, b)
    single = [once(a[k:k + 1], b[k:k + 1]) for k in range(min(batch, 8)) for _ in range(repeats)]
    batched = [once(a, b) / batch for _ in range(repeats)]
    return {"num_points": registrar.num_points, "batch": batch, "ms_batch1": 1e3 * float(np.median(single)),
            "ms_per_pair_batched": 1e3 * float(np.median(batched))}
