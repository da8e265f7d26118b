"""Benchmark datasets: the paper's tables as a registry, the suites' pair counts, and each pair's truth.

A dataset (`DatasetSpec`) builds an indexable set of pair dicts (source, target, transform: the 4x4
target_from_source truth, x_t = R x_s + t; conventions in `genreg_core.geometry`) and names the GenReg
checkpoint kind used on it ("object": ModelNet40, "scene": 7-Scenes and SUN3D), its units, baseline
settings and success rule. A suite picks how many pairs of each dataset a run registers (`plan_pairs`:
evenly spread picks, so a few pairs still span categories and frames). `pair_truth` holds what a record
is scored against: the true transform and the Chamfer-distance points, the same for every method.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

import numpy as np
from torch.utils.data import ConcatDataset

from genreg_core.bench.baselines import BaselineParams
from genreg_core.data import (
    REDKITCHEN_VAL_FRAMES,
    FMRPairs,
    FramePairs,
    ModelNetPairs,
    RGBDSequence,
    load_modelnet40,
)
from genreg_core.geometry import apply_transform
from genreg_core.metrics import chamfer_distance, transform_errors

OBJECT, SCENE = "object", "scene"


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
def modelnet_shapes(categories: str, root: str | None) -> Any:
    """The ModelNet40 test-split shapes of "seen" or "unseen" categories (cached: suites reuse them)."""
    return load_modelnet40("test", categories, root)


def modelnet_pairs(categories: str, variant: str) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        return ModelNetPairs(modelnet_shapes(categories, o.data_root), o.object_points, variant, seed=o.seed)

    return build


def frame_pairs(names: Sequence[str], gap: int, frames: Sequence[int] | None = None) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        sets = [FramePairs(RGBDSequence.open(n, o.data_root), gap, frames, stride=o.frame_stride) for n in names]
        return sets[0] if len(sets) == 1 else ConcatDataset(sets)

    return build


def fmr_pairs(o: BenchOptions) -> Any:
    return FMRPairs(RGBDSequence.redkitchen(o.data_root), REDKITCHEN_VAL_FRAMES, o.fmr_points, seed=o.seed)


def dataset_specs() -> dict[str, DatasetSpec]:
    specs = []
    for cats, label in (("seen", "seen categories (test split)"), ("unseen", "unseen categories")):
        for variant in ("clean", "noise", "partial"):
            specs.append(DatasetSpec(
                f"modelnet-{cats}-{variant}", f"ModelNet40 {label}, {variant}", OBJECT, False,
                modelnet_pairs(cats, variant),
            ))
    val = REDKITCHEN_VAL_FRAMES
    stairs = [f"stairs-{k}" for k in range(1, 5)]
    specs += [
        DatasetSpec("redkitchen-fmr", "7-Scenes redkitchen validation, FMR-style pairs", SCENE, False, fmr_pairs),
        DatasetSpec("redkitchen-gap1", "7-Scenes redkitchen validation, frame pairs gap 1", SCENE, True,
                    frame_pairs(["redkitchen"], 1, val)),
        DatasetSpec("redkitchen-gap10", "7-Scenes redkitchen validation, frame pairs gap 10", SCENE, True,
                    frame_pairs(["redkitchen"], 10, val)),
        DatasetSpec("stairs-gap1", "Unseen scene 7-Scenes stairs, gap 1", SCENE, True, frame_pairs(stairs, 1)),
        DatasetSpec("stairs-gap2", "Unseen scene 7-Scenes stairs, gap 2", SCENE, True, frame_pairs(stairs, 2)),
        DatasetSpec("sun3d-gap5", "Unseen scene SUN3D, gap 5", SCENE, True, frame_pairs(["sun3d-1", "sun3d-2"], 5)),
    ]
    return {s.name: s for s in specs}


DATASETS: dict[str, DatasetSpec] = dataset_specs()


@dataclass(frozen=True)
class Suite:
    """Pairs per dataset (None: all of them, evenly spread picks otherwise) and option overrides."""

    counts: dict[str, int | None]
    options: dict[str, Any] = field(default_factory=dict)


MODELNET = [n for n in DATASETS if n.startswith("modelnet")]
SUITES: dict[str, Suite] = {
    # A few pairs end to end (CI): quarter-resolution frames keep it to seconds.
    "smoke": Suite({"modelnet-unseen-clean": 3, "modelnet-seen-partial": 2, "redkitchen-fmr": 2,
                    "redkitchen-gap10": 1}, {"frame_stride": 4}),
    # < 10 minutes on 2 cores.
    "quick": Suite({**{n: 25 for n in MODELNET}, "redkitchen-fmr": 25, "redkitchen-gap1": 8,
                    "redkitchen-gap10": 8, "stairs-gap1": None, "stairs-gap2": None, "sun3d-gap5": 8}),
    # < 60 minutes on 2 cores.
    "full": Suite({**{n: 200 for n in MODELNET}, "redkitchen-fmr": 200, "redkitchen-gap1": 66,
                   "redkitchen-gap10": 64, "stairs-gap1": None, "stairs-gap2": None, "sun3d-gap5": 45}),
}


def select_indices(total: int, count: int | None) -> list[int]:
    """All indices, or `count` evenly spread ones (first and last included): spans categories/frames."""
    if count is None or count >= total:
        return list(range(total))
    return sorted({round(x) for x in np.linspace(0, total - 1, count)})


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


def plan_suite(
    suite: str | Suite, options: BenchOptions | None, datasets: Sequence[str] | None, max_pairs: int | None
) -> tuple[str, BenchOptions, list[tuple[DatasetSpec, Any, list[int]]]]:
    """(suite name, options with its overrides, `plan_pairs` of its datasets, restricted to `datasets`)."""
    suite_name, spec_suite, options = resolve_suite(suite, options)
    names = [n for n in spec_suite.counts if datasets is None or n in datasets]
    return suite_name, options, plan_pairs(spec_suite, names, options, max_pairs)


@dataclass(frozen=True)
class PairTruth:
    """What an estimate of one pair is scored against: the true 4x4 target_from_source and the Chamfer
    points (at most `cd_points` random points per cloud, the same for every method and table)."""

    transform: np.ndarray
    source_cd: np.ndarray
    target_cd: np.ndarray

    @property
    def cd_floor(self) -> float:
        """The Chamfer distance at the true pose."""
        return chamfer_distance(apply_transform(self.transform, self.source_cd), self.target_cd)

    def errors(self, T: np.ndarray) -> tuple[float, float, float]:
        """(RE deg, TE, CD) of an estimate; NaN for a non-finite transform."""
        if not np.isfinite(T).all():
            return float("nan"), float("nan"), float("nan")
        re, te = transform_errors(T, self.transform)
        return re, te, chamfer_distance(apply_transform(T, self.source_cd), self.target_cd)


def pair_truth(item: dict[str, Any], index: int, options: BenchOptions) -> PairTruth:
    """The truth of pair `index` of a dataset; its CD points are drawn with the seed (options.seed, index)."""
    rng = np.random.default_rng((options.seed, index))

    def cd_subset(points: np.ndarray) -> np.ndarray:
        points = points.astype(np.float64)
        n = options.cd_points
        return points if len(points) <= n else points[rng.choice(len(points), n, replace=False)]

    source_cd = cd_subset(item["source"])
    return PairTruth(np.asarray(item["transform"], dtype=np.float64), source_cd, cd_subset(item["target"]))
