"""ModelNet40 shapes and the paper's synthetic registration pairs (GenReg Sec. 4.1).

Data: `<data_root>/modelnet40/{train,test}.npz` (1024 float16 points per shape, unit sphere, z up) and
`modelnet40_shape_names.txt` (label i = line i). Seen categories are the first 20 names, unseen the
last 20. `train.npz` holds only seen categories (the complete official train split); the paper's 8:2
seen split is train.npz (train) vs the seen part of test.npz (test). Unseen shapes exist only in
test.npz and must never be trained on.

Pairs (`ModelNetPairs`): the shape is put into the unit box [0, 1]^3 once; source and target are two
independent draws of N of its points; `transform` is T_target_source, i.e. target = R source + t
(x' = R x + t on column vectors, `geometry.apply_transform` on rows). Units: unit-box units.

Partial-to-partial pairs (`rpmnet_crop_pair`, variant "crop"), RPM-Net's protocol at the stored
unit-sphere scale: source and target are two independent 768-point subsets of the 1024 points, each
cropped to 70 % by its own random plane (the points with the largest projection on a random unit
direction, measured from the centroid), Gaussian noise sigma 0.01 clipped at 0.05 on both, rotation by
Euler angles each uniform in [0, 45] deg, translation uniform in [-0.5, 0.5] per axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from torch.utils.data import Dataset

from genreg_core.config import data_root
from genreg_core.errors import ConfigError, DataNotFoundError
from genreg_core.geometry import (
    apply_transform,
    make_transform,
    normalize_pair,
    random_transform,
    unit_box_normalization,
)

NUM_SEEN = 20
POINTS_PER_SHAPE = 1024
SPLITS = ("train", "test")
CATEGORY_SETS = ("seen", "unseen", "all")
VARIANTS = ("clean", "noise", "partial", "crop")


@dataclass(frozen=True)
class ModelNetShapes:
    """Shapes of one split. points (S, 1024, 3) float32 (unit sphere, z up), labels (S,) int64 indexing
    `class_names` (all 40 names, file order), names (S,) shape ids such as 'airplane_0627'."""

    points: np.ndarray
    labels: np.ndarray
    names: np.ndarray
    class_names: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.labels)


def modelnet40_dir(root: str | Path | None = None) -> Path:
    """`<data_root>/modelnet40`; `root` is the data root, and env GENREG_DATA overrides it (config.data_root)."""
    folder = data_root(root) / "modelnet40"
    if not folder.is_dir():
        raise DataNotFoundError(f"ModelNet40 folder not found: {folder} (set GENREG_DATA or data_root)")
    return folder


def load_class_names(root: str | Path | None = None) -> tuple[str, ...]:
    """The 40 category names in label order (seen = first 20, unseen = last 20)."""
    path = modelnet40_dir(root) / "modelnet40_shape_names.txt"
    if not path.is_file():
        raise DataNotFoundError(f"missing {path}")
    names = tuple(path.read_text().split())
    if len(names) != 2 * NUM_SEEN:
        raise DataNotFoundError(f"{path} lists {len(names)} categories, expected 40")
    return names


def load_modelnet40(split: str, categories: str = "seen", root: str | Path | None = None) -> ModelNetShapes:
    """Load a split ('train' | 'test') restricted to 'seen' | 'unseen' | 'all' categories.

    The train split has seen categories only: asking for 'unseen' or 'all' train shapes raises ConfigError.
    """
    if split not in SPLITS:
        raise ConfigError(f"split must be one of {SPLITS}, got {split!r}")
    if categories not in CATEGORY_SETS:
        raise ConfigError(f"categories must be one of {CATEGORY_SETS}, got {categories!r}")
    if split == "train" and categories != "seen":
        raise ConfigError(
            f"ModelNet40 train split has only the {NUM_SEEN} seen categories; unseen shapes are test-only "
            f"(nothing may train on them): use categories='seen', not {categories!r}"
        )
    class_names = load_class_names(root)
    path = modelnet40_dir(root) / f"{split}.npz"
    if not path.is_file():
        raise DataNotFoundError(f"missing {path}")
    with np.load(path) as data:
        labels = data["labels"].astype(np.int64)
        if categories == "seen":
            keep = labels < NUM_SEEN
        elif categories == "unseen":
            keep = labels >= NUM_SEEN
        else:
            keep = np.ones(len(labels), dtype=bool)
        points = data["points"][keep].astype(np.float32)
        names = data["names"][keep]
    return ModelNetShapes(points=points, labels=labels[keep], names=names, class_names=class_names)


def crop_by_plane(points: np.ndarray, keep: float, rng: np.random.Generator) -> np.ndarray:
    """The `keep` share of `points` with the largest projection on a random unit direction (from the
    centroid): the part of the shape on one side of a random plane."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    projection = (points - points.mean(axis=0)) @ direction
    count = int(np.ceil(keep * len(points)))
    return points[np.sort(np.argsort(-projection, kind="stable")[:count])]


def rpmnet_crop_pair(
    shape: np.ndarray, rng: np.random.Generator, subset: int = 768, keep: float = 0.7,
    noise_sigma: float = 0.01, noise_clip: float = 0.05, max_angle_deg: float = 45.0,
    max_translation: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One partial-to-partial pair of a unit-sphere shape (module docstring): (source, target,
    T_target_source), float64, at the shape's stored scale."""
    clouds = []
    for _ in range(2):
        cloud = crop_by_plane(shape[rng.permutation(len(shape))[:subset]], keep, rng)
        clouds.append(cloud + np.clip(rng.normal(0.0, noise_sigma, cloud.shape), -noise_clip, noise_clip))
    angles = rng.uniform(0.0, max_angle_deg, size=3)
    T = make_transform(Rotation.from_euler("xyz", angles, degrees=True).as_matrix(),
                       rng.uniform(-max_translation, max_translation, size=3))
    return clouds[0], apply_transform(T, clouds[1]), T


class ModelNetPairs(Dataset):
    """Synthetic registration pairs from ModelNet40 shapes (paper Sec. 4.1); numpy in, numpy float32 out.

    Item i -> dict(source (N, 3), target (N, 3), transform (4, 4) T_target_source, label, variant):
    the shape is normalised into [0, 1]^3 once; source and target are independent random subsets of
    N < 1024 of its points (independent permutations at N = 1024); target = R subset + t with
    T = `random_transform(rng, max_angle_deg, max_translation)`.
    Variants (target only): 'noise' adds N(0, noise_sigma^2) per coordinate; 'partial' first drops the
    `partial_ratio` of the shape's points with the largest x (object frame, before T), then draws N.
    Variant 'crop' (both clouds): `rpmnet_crop_pair` at the stored scale (its own rotation and
    translation ranges), then normalised like the registration pipeline does (the source fills the unit
    box, `geometry.normalize_pair`) and subsampled to N.
    A tuple of variants picks one per item. Item i uses `np.random.default_rng((seed, epoch, i))`;
    `set_epoch` changes the draws, and `max_angle_deg` may be changed between epochs (curriculum).
    With DataLoader workers, call `set_epoch` before creating the iterator (no persistent workers).
    """

    def __init__(
        self,
        shapes: ModelNetShapes,
        num_points: int = 512,
        variant: str | Sequence[str] = "clean",
        max_angle_deg: float = 45.0,
        max_translation: float = 0.8,
        noise_sigma: float = 0.01,
        partial_ratio: float = 0.2,
        seed: int = 0,
    ) -> None:
        variants = (variant,) if isinstance(variant, str) else tuple(variant)
        if not variants or any(v not in VARIANTS for v in variants):
            raise ConfigError(f"variant must be one of {VARIANTS} or a tuple of them, got {variant!r}")
        total = shapes.points.shape[1]
        if not 0.0 <= partial_ratio < 1.0:
            raise ConfigError(f"partial_ratio must be in [0, 1), got {partial_ratio}")
        self.num_dropped = round(partial_ratio * total)
        available = total - self.num_dropped if "partial" in variants else total
        if not 1 <= num_points <= available:
            raise ConfigError(
                f"num_points must be in [1, {available}] for variants {variants}, got {num_points}"
            )
        if max_angle_deg < 0 or max_translation < 0 or noise_sigma < 0:
            raise ConfigError("max_angle_deg, max_translation and noise_sigma must be >= 0")
        self.shapes = shapes
        self.num_points = int(num_points)
        self.variants = variants
        self.max_angle_deg = float(max_angle_deg)
        self.max_translation = float(max_translation)
        self.noise_sigma = float(noise_sigma)
        self.partial_ratio = float(partial_ratio)
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Select the random draws of epoch `epoch` (item i uses rng (seed, epoch, i))."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.shapes)

    def __getitem__(self, index: int) -> dict:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for {n} pairs")
        index = int(index) % n
        rng = np.random.default_rng((self.seed, self.epoch, index))
        variant = (
            self.variants[0] if len(self.variants) == 1 else self.variants[rng.integers(len(self.variants))]
        )

        shape = self.shapes.points[index].astype(np.float64)
        if variant == "crop":
            src, tgt, T = rpmnet_crop_pair(shape, rng)
            src_n, tgt_n, T_n, _, _ = normalize_pair(src, tgt, T)
            pick = [rng.choice(len(c), self.num_points, replace=len(c) < self.num_points) for c in (src_n, tgt_n)]
            return {"source": src_n[pick[0]], "target": tgt_n[pick[1]], "transform": T_n.astype(np.float32),
                    "label": int(self.shapes.labels[index]), "variant": variant}
        offset, scale = unit_box_normalization(shape)
        shape = (shape - offset) / scale
        T = random_transform(rng, self.max_angle_deg, self.max_translation)
        total = len(shape)
        source_idx = rng.permutation(total)[: self.num_points]
        pool = np.arange(total)
        if variant == "partial" and self.num_dropped > 0:
            pool = np.sort(np.argsort(shape[:, 0], kind="stable")[: total - self.num_dropped])
        target_idx = pool[rng.permutation(len(pool))[: self.num_points]]
        target = apply_transform(T, shape[target_idx])
        if variant == "noise":
            target = target + rng.normal(0.0, self.noise_sigma, size=target.shape)
        return {
            "source": shape[source_idx].astype(np.float32),
            "target": target.astype(np.float32),
            "transform": T.astype(np.float32),
            "label": int(self.shapes.labels[index]),
            "variant": variant,
        }


def balanced_sampler_indices(labels: np.ndarray, num_samples: int, rng: np.random.Generator) -> np.ndarray:
    """`num_samples` shape indices, category-balanced: every present label gets num_samples // C draws
    (the remainder goes to randomly chosen labels), shapes drawn uniformly with replacement within a
    label, returned in random order (int64). Use with `torch.utils.data.Subset` or a sampler."""
    labels = np.asarray(labels)
    if labels.ndim != 1 or len(labels) == 0:
        raise ConfigError("labels must be a non-empty 1-D array")
    if num_samples < 0:
        raise ConfigError(f"num_samples must be >= 0, got {num_samples}")
    classes, inverse = np.unique(labels, return_inverse=True)
    num_classes = len(classes)
    order = np.argsort(inverse, kind="stable")  # shape indices grouped by class
    counts = np.bincount(inverse, minlength=num_classes)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    per_draw = np.concatenate(
        [
            np.repeat(np.arange(num_classes), num_samples // num_classes),
            rng.choice(num_classes, num_samples % num_classes, replace=False),
        ]
    ).astype(np.int64)
    within = np.floor(rng.random(num_samples) * counts[per_draw]).astype(np.int64)
    picks = order[starts[per_draw] + within]
    return rng.permutation(picks).astype(np.int64)
