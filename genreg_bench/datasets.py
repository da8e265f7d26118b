"""Benchmark datasets: the paper's tables as a registry, the suites' pair counts, and each pair's truth.

A dataset (`DatasetSpec`) builds an indexable set of pair dicts (source, target, transform: the 4x4
target_from_source truth, x_t = R x_s + t; conventions in `genreg_core.geometry`; ModelNet40 pairs also
name their `category`) and names the GenReg checkpoint kind used on it ("object": ModelNet40, "scene":
7-Scenes and SUN3D) and its `Frame`: units, success rule, baseline settings, overlap radius and the
methods that do not apply there. A suite picks how many pairs of each dataset a run registers
(`plan_pairs`: evenly spread picks, so a few pairs still span categories and frames) and its default
methods. `pair_truth` holds what a record is scored against: the true transform, the Chamfer-distance
points and the pair's overlap share, the same for every method.

Partial-overlap datasets:
- `modelnet-rpmnet-{seen,unseen}` (`RPMNetPairs`): RPM-Net-style partial-to-partial pairs
  (`data.modelnet40.rpmnet_crop_pair`: two 768-point subsets, each cropped to 70 % by its own plane,
  noise, Euler angles in [0, 45] deg, translation in [-0.5, 0.5]) at the stored unit-sphere scale;
  seen = test split of the first 20 categories, unseen = the last 20. Success: RE < 5 deg (no TE rule).
- `redkitchen-kidnap-gap{30,60,90}` (validation frames 800-999) and `sun3d-kidnap-gap{5,20}` (both
  fragments) (`KidnapPairs`): frame pairs (i, i + gap), source = frame i + gap, moved by a random rigid
  motion (`kidnap_motion`: angle in [0, 45] deg about a random axis through the source centroid, then a
  translation of random direction and length in [0, 0.5] m); the truth includes the motion. Success:
  RE < 2 deg and TE < 5 cm.
Overlap share (`overlap_share`): the share of source points with a target point within the frame's
`overlap_radius` at the true pose: 5 cm on metric frames, 0.05 on the unit sphere (5 % of its radius),
0.025 in the unit box (the same share of a shape: the unit box is the sphere's bounding box halved).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from torch.utils.data import ConcatDataset, Dataset

from genreg_bench.baselines import BaselineParams
from genreg_core.data import (
    REDKITCHEN_VAL_FRAMES,
    FMRPairs,
    FramePairs,
    ModelNetPairs,
    ModelNetShapes,
    RGBDSequence,
    load_modelnet40,
)
from genreg_core.data.modelnet40 import rpmnet_crop_pair
from genreg_core.geometry import apply_transform, invert_transform, kidnap_motion
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
UNIT_SPHERE_SUCCESS = Success(5.0, math.inf)  # RPM-Net-style objects: the rotation decides
KIDNAP_SUCCESS = Success(2.0, 0.05)  # kidnapped real frame pairs, metres
# Symmetric ModelNet40 categories: their pose is ambiguous, so tables also give means without them.
SYMMETRIC_CATEGORIES = ("bottle", "bowl", "cone", "cup", "flower_pot", "lamp", "tent", "vase")
# fpfh+ransac+icp-accurate's 2.5 cm voxels are a metric setting; truth+gicp measures real frames' pose errors
SCENE_ONLY_METHODS = frozenset({"fpfh+ransac+icp-accurate", "truth+gicp"})


@dataclass(frozen=True)
class Frame:
    """A dataset's units: name, success rule, baseline settings (`params(threads)`), the radius of the
    overlap share (those units) and the methods that do not apply in them."""

    units: str
    success: Success
    params: Callable[[int], BaselineParams]
    overlap_radius: float
    excluded: frozenset[str] = frozenset()


UNIT_BOX = Frame("unit box", UNIT_BOX_SUCCESS, BaselineParams.unit_box, 0.025, SCENE_ONLY_METHODS)
UNIT_SPHERE = Frame("unit sphere", UNIT_SPHERE_SUCCESS, BaselineParams.unit_sphere, 0.05, SCENE_ONLY_METHODS)
METRIC = Frame("m", METRIC_SUCCESS, BaselineParams.metric_scene, 0.05)
KIDNAP = Frame("m", KIDNAP_SUCCESS, BaselineParams.metric_scene, 0.05)


@dataclass(frozen=True)
class BenchOptions:
    """Pair generation and measurement settings shared by every dataset of a run."""

    object_points: int = 512  # N per ModelNet40 cloud (independent subsets of the 1024 points)
    fmr_points: int = 1024  # N per FMR-style cloud (two independent subsets of one frame)
    frame_stride: int | None = None  # real frames: every stride-th pixel (None: the suite's, else 1 = full, ~300k)
    seed: int = 0  # pair draws, GenReg sampling and CD subsets
    cd_points: int = 4096  # CD on at most this many random points per cloud
    threads: int = 2  # reported, and small_gicp's worker count
    throughput_batch: int = 16  # batched GenReg throughput: pairs per forward pass
    data_root: str | None = None  # None: GENREG_DATA or ../shared/data


@dataclass(frozen=True)
class DatasetSpec:
    """One table: which pairs, which GenReg checkpoint kind, and its `Frame` (units, baseline settings,
    success rule, overlap radius, methods that apply)."""

    name: str
    title: str
    kind: str  # OBJECT or SCENE: the checkpoint GenReg uses here
    frame: Frame
    build: Callable[[BenchOptions], Any]  # -> indexable set of pair dicts (source, target, transform)

    @property
    def metric(self) -> bool:
        return self.frame.units == "m"

    @property
    def units(self) -> str:
        return self.frame.units

    @property
    def success(self) -> Success:
        return self.frame.success

    def baseline_params(self, threads: int) -> BaselineParams:
        return self.frame.params(threads)

    def applies(self, method: str) -> bool:
        """Whether `method` runs on this dataset (not every baseline setting fits every scale)."""
        return method not in self.frame.excluded


@lru_cache(maxsize=4)
def modelnet_shapes(categories: str, root: str | None) -> Any:
    """The ModelNet40 test-split shapes of "seen" or "unseen" categories (cached: suites reuse them)."""
    return load_modelnet40("test", categories, root)


class Categorized(Dataset):
    """ModelNet40 pairs with each item's category name (`category`) added, for the symmetric-category means."""

    def __init__(self, pairs: Any, shapes: ModelNetShapes) -> None:
        self.pairs, self.shapes = pairs, shapes

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, Any]:
        item = self.pairs[index]
        return {**item, "category": self.shapes.class_names[item["label"]]}


class RPMNetPairs(Dataset):
    """RPM-Net-style partial-to-partial pairs of ModelNet40 shapes at their stored unit-sphere scale.

    Item i -> dict(source, target (about 538 points each, float32), transform (4, 4) float64
    T_target_source, label, category): `rpmnet_crop_pair` of shape i with rng (seed, 1, i).
    """

    def __init__(self, shapes: ModelNetShapes, seed: int = 0) -> None:
        self.shapes, self.seed = shapes, int(seed)

    def __len__(self) -> int:
        return len(self.shapes)

    def __getitem__(self, index: int) -> dict[str, Any]:
        rng = np.random.default_rng((self.seed, 1, int(index)))
        source, target, T = rpmnet_crop_pair(self.shapes.points[index].astype(np.float64), rng)
        label = int(self.shapes.labels[index])
        return {"source": source.astype(np.float32), "target": target.astype(np.float32), "transform": T,
                "label": label, "category": self.shapes.class_names[label]}


class KidnapPairs(Dataset):
    """Frame pairs whose source is moved by a further random rigid motion (`kidnap_motion` about the source
    centroid, rng (seed, 2, k) for item k of the concatenated sets): source = M source_frame, transform =
    T_target_source M^-1 (float64); the item keeps `kidnap` = M."""

    def __init__(self, sets: Sequence[FramePairs], seed: int = 0) -> None:
        self.pairs, self.seed = ConcatDataset(list(sets)), int(seed)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, Any]:
        item = self.pairs[index]
        source = item["source"].astype(np.float64)
        M = kidnap_motion(np.random.default_rng((self.seed, 2, int(index))), source.mean(axis=0))
        transform = item["transform"].astype(np.float64) @ invert_transform(M)
        return {**item, "source": apply_transform(M, source).astype(np.float32), "transform": transform,
                "kidnap": M}


def modelnet_pairs(categories: str, variant: str) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        shapes = modelnet_shapes(categories, o.data_root)
        return Categorized(ModelNetPairs(shapes, o.object_points, variant, seed=o.seed), shapes)

    return build


def rpmnet_pairs(categories: str) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        return RPMNetPairs(modelnet_shapes(categories, o.data_root), seed=o.seed)

    return build


def frame_sets(names: Sequence[str], gap: int, frames: Sequence[int] | None, o: BenchOptions) -> list[FramePairs]:
    return [FramePairs(RGBDSequence.open(n, o.data_root), gap, frames, stride=o.frame_stride or 1) for n in names]


def frame_pairs(names: Sequence[str], gap: int, frames: Sequence[int] | None = None) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        sets = frame_sets(names, gap, frames, o)
        return sets[0] if len(sets) == 1 else ConcatDataset(sets)

    return build


def kidnap_pairs(names: Sequence[str], gap: int, frames: Sequence[int] | None = None) -> Callable[[BenchOptions], Any]:
    def build(o: BenchOptions) -> Any:
        return KidnapPairs(frame_sets(names, gap, frames, o), seed=o.seed)

    return build


def fmr_pairs(o: BenchOptions) -> Any:
    return FMRPairs(RGBDSequence.redkitchen(o.data_root), REDKITCHEN_VAL_FRAMES, o.fmr_points, seed=o.seed)


def dataset_specs() -> dict[str, DatasetSpec]:
    specs = []
    for cats, label in (("seen", "seen categories (test split)"), ("unseen", "unseen categories")):
        for variant in ("clean", "noise", "partial"):
            specs.append(DatasetSpec(
                f"modelnet-{cats}-{variant}", f"ModelNet40 {label}, {variant}", OBJECT, UNIT_BOX,
                modelnet_pairs(cats, variant),
            ))
        specs.append(DatasetSpec(f"modelnet-rpmnet-{cats}", f"ModelNet40 {label}, RPM-Net-style partial-to-partial",
                                 OBJECT, UNIT_SPHERE, rpmnet_pairs(cats)))
    val = REDKITCHEN_VAL_FRAMES
    stairs = [f"stairs-{k}" for k in range(1, 5)]
    sun3d = ["sun3d-1", "sun3d-2"]
    specs += [
        DatasetSpec("redkitchen-fmr", "7-Scenes redkitchen validation, FMR-style pairs", SCENE, UNIT_BOX, fmr_pairs),
        DatasetSpec("redkitchen-gap1", "7-Scenes redkitchen validation, frame pairs gap 1", SCENE, METRIC,
                    frame_pairs(["redkitchen"], 1, val)),
        DatasetSpec("redkitchen-gap10", "7-Scenes redkitchen validation, frame pairs gap 10", SCENE, METRIC,
                    frame_pairs(["redkitchen"], 10, val)),
        DatasetSpec("stairs-gap1", "Unseen scene 7-Scenes stairs, gap 1", SCENE, METRIC, frame_pairs(stairs, 1)),
        DatasetSpec("stairs-gap2", "Unseen scene 7-Scenes stairs, gap 2", SCENE, METRIC, frame_pairs(stairs, 2)),
        DatasetSpec("sun3d-gap5", "Unseen scene SUN3D, gap 5", SCENE, METRIC, frame_pairs(sun3d, 5)),
    ]
    for gap in (30, 60, 90):
        specs.append(DatasetSpec(f"redkitchen-kidnap-gap{gap}", f"7-Scenes redkitchen validation, gap {gap}, kidnapped",
                                 SCENE, KIDNAP, kidnap_pairs(["redkitchen"], gap, val)))
    for gap in (5, 20):
        specs.append(DatasetSpec(f"sun3d-kidnap-gap{gap}", f"Unseen scene SUN3D, gap {gap}, kidnapped", SCENE, KIDNAP,
                                 kidnap_pairs(sun3d, gap)))
    return {s.name: s for s in specs}


DATASETS: dict[str, DatasetSpec] = dataset_specs()


@dataclass(frozen=True)
class Suite:
    """Pairs per dataset (None: all of them, evenly spread picks otherwise), option overrides (they fill the
    options a caller left None), the default methods (None: `methods.DEFAULT_METHODS`) and a name for the
    report (None: "custom")."""

    counts: dict[str, int | None]
    options: dict[str, Any] = field(default_factory=dict)
    methods: tuple[str, ...] | None = None
    name: str | None = None

    def with_pairs(self, name: str, pairs: int) -> Suite:
        """The same suite, named `name`, with `pairs` pairs of every dataset."""
        return replace(self, counts=dict.fromkeys(self.counts, pairs), name=name)


# Kidnapped scene pairs per dataset in the partial suite: at full resolution every baseline takes seconds
# per pair (2 threads, shared machine: redkitchen ~40 s for all methods, SUN3D ~170 s, most of it
# fpfh+ransac+icp-accurate's RANSAC on ~35k 2.5 cm voxels), so the suite stays well under an hour.
PARTIAL_PAIRS = {"redkitchen-kidnap-gap30": 12, "redkitchen-kidnap-gap60": 12, "redkitchen-kidnap-gap90": 12,
                 "sun3d-kidnap-gap5": 5, "sun3d-kidnap-gap20": 5}
MODELNET = [f"modelnet-{c}-{v}" for c in ("seen", "unseen") for v in ("clean", "noise", "partial")]
RPMNET = ["modelnet-rpmnet-seen", "modelnet-rpmnet-unseen"]
# The partial-overlap comparison: GenReg (alone, + point-to-point, + point-to-plane, + GICP: the node's scene setting)
# beside the partial-overlap baselines.
PARTIAL_METHODS = ("identity", "truth+gicp", "genreg", "genreg+icp", "genreg+p2plane", "genreg+gicp", "icp-p2plane",
                   "fpfh+ransac+icp", "fpfh+ransac+icp-accurate", "kiss-matcher+p2plane", "small_gicp")
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
    # The partial-overlap tables at full frame resolution, well under an hour on 2 cores.
    "partial": Suite({**{n: 100 for n in RPMNET}, **PARTIAL_PAIRS}, methods=PARTIAL_METHODS),
}


def select_indices(total: int, count: int | None) -> list[int]:
    """All indices, or `count` evenly spread ones (first and last included): spans categories/frames."""
    if count is None or count >= total:
        return list(range(total))
    return sorted({round(x) for x in np.linspace(0, total - 1, count)})


def resolve_suite(suite: str | Suite, options: BenchOptions | None) -> tuple[str, Suite, BenchOptions]:
    """(name, Suite, options) of a suite name or a custom `Suite`: the suite's overrides fill the options
    left None, and an unset frame stride is 1 (full resolution)."""
    spec_suite = SUITES[suite] if isinstance(suite, str) else suite
    options = options or BenchOptions()
    options = replace(options, **{k: v for k, v in spec_suite.options.items() if getattr(options, k) is None})
    if options.frame_stride is None:
        options = replace(options, frame_stride=1)
    return suite if isinstance(suite, str) else suite.name or "custom", spec_suite, options


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
    """(suite name, options with its overrides, `plan_pairs` of its datasets, restricted to `datasets`);
    ValueError for a dataset the suite does not hold."""
    suite_name, spec_suite, options = resolve_suite(suite, options)
    outside = [n for n in datasets or () if n not in spec_suite.counts]
    if outside:
        holders = {n: [k for k, v in SUITES.items() if n in v.counts] for n in outside}
        raise ValueError(f"suite {suite_name!r} does not hold datasets {outside} (suites holding them: {holders})")
    names = [n for n in spec_suite.counts if datasets is None or n in datasets]
    return suite_name, options, plan_pairs(spec_suite, names, options, max_pairs)


def overlap_share(source: np.ndarray, target: np.ndarray, transform: np.ndarray, radius: float) -> float:
    """The share of `source` points with a `target` point within `radius` once moved by `transform`
    (target_from_source, the true pose): the pair's overlap, in [0, 1]."""
    moved = apply_transform(np.asarray(transform, dtype=np.float64), np.asarray(source, dtype=np.float64))
    distance, _ = cKDTree(np.asarray(target, dtype=np.float64)).query(moved, distance_upper_bound=radius)
    return float(np.mean(distance <= radius))


@dataclass(frozen=True)
class PairTruth:
    """What an estimate of one pair is scored against: the true 4x4 target_from_source and the Chamfer
    points (at most `cd_points` random points per cloud, the same for every method and table); `overlap`:
    the pair's `overlap_share` (the CD source points against the whole target), None if not measured."""

    transform: np.ndarray
    source_cd: np.ndarray
    target_cd: np.ndarray
    overlap: float | None = None

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


def pair_truth(item: dict[str, Any], index: int, options: BenchOptions,
               overlap_radius: float | None = None) -> PairTruth:
    """The truth of pair `index` of a dataset; its CD points are drawn with the seed (options.seed, index).
    With `overlap_radius`, the overlap share of the CD source points (all of the target) is measured."""
    rng = np.random.default_rng((options.seed, index))

    def cd_subset(points: np.ndarray) -> np.ndarray:
        points = points.astype(np.float64)
        n = options.cd_points
        return points if len(points) <= n else points[rng.choice(len(points), n, replace=False)]

    T = np.asarray(item["transform"], dtype=np.float64)
    source_cd = cd_subset(item["source"])
    overlap = None if overlap_radius is None else overlap_share(source_cd, item["target"], T, overlap_radius)
    return PairTruth(T, source_cd, cd_subset(item["target"]), overlap)
