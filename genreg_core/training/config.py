"""Training configuration (YAML -> typed dataclasses). Every training default lives here."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from genreg_core.config import ModelConfig, PDSACConfig, _check, from_dict


@dataclass(frozen=True)
class DataConfig:
    dataset: str = "modelnet40"  # "modelnet40" or "7scenes"
    variants: tuple[str, ...] = ("clean", "noise", "partial")  # mixed per item (ModelNet40)
    validation_variant: str = "clean"  # ModelNet40 validation pairs (seen-category test split): clean, crop, ...
    pair_modes: tuple[str, ...] = ("fmr", "frames")  # 7-Scenes: FMR-style and real frame pairs
    frame_gaps: tuple[int, ...] = (1, 5, 10)  # 7-Scenes real pairs (i, i+g)
    frame_kidnap: bool = False  # 7-Scenes real pairs: source moved by a random kidnap motion (<= 45 deg, 0.5 m)
    validation_frame_gap: int = 10  # 7-Scenes validation pairs (frames 800-999): this gap
    max_angle_deg: float = 45.0  # the paper's rotation range
    max_translation: float = 0.8
    balanced: bool = True  # category-balanced sampling (ModelNet40)
    root: str | None = None  # data folder; GENREG_DATA overrides

    def __post_init__(self) -> None:
        _check(self.dataset in ("modelnet40", "7scenes"), "data.dataset must be 'modelnet40' or '7scenes'")


@dataclass(frozen=True)
class LossWeights:
    """Weights of the total loss; the paper: 1, 1, 1, 0.01, 1 (correspondence and matching are our levers, 0 there)."""

    absolute: float = 1.0
    relative: float = 1.0
    cycle: float = 1.0
    adversarial: float = 0.01
    transformation: float = 1.0
    correspondence: float = 0.0
    matching: float = 0.0  # our lever: soft-pointer cross-entropy (architecture "genreg" only)
    matching_sigma: float = 0.05  # width of the true soft match, unit-box units (~ the point spacing)
    overlap: float = 0.0  # our lever: overlap-head binary cross-entropy (models with an overlap head)
    overlap_radius: float = 0.05  # a point overlaps when the other cloud has a point this close (unit box)


@dataclass(frozen=True)
class GanConfig:
    mode: str = "gan"  # "gan" (log loss) or "wgan-gp"
    generator_every: int = 5  # paper: discriminator every step, generator every 5 steps
    gradient_penalty: float = 10.0  # WGAN-GP lambda
    lr: float = 1e-4

    def __post_init__(self) -> None:
        _check(self.mode in ("gan", "wgan-gp"), "gan.mode must be 'gan' or 'wgan-gp'")
        _check(self.generator_every >= 1, "gan.generator_every must be >= 1")


@dataclass(frozen=True)
class ScheduleConfig:
    steps: int = 20000  # generator updates
    batch_size: int = 8
    lr: float = 1e-3
    warmup_steps: int = 200
    min_lr_ratio: float = 0.05  # cosine decay to lr * min_lr_ratio
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    curriculum_steps: int = 0  # ramp max_angle_deg from curriculum_start_deg over these steps (0: off)
    curriculum_start_deg: float = 10.0


@dataclass(frozen=True)
class TrainConfig:
    name: str = "modelnet40"
    out_dir: str = "runs/modelnet40"
    seed: int = 0
    threads: int = 2
    init_from: str | None = None  # warm start: generator weights from this checkpoint (fresh optimiser)
    model: ModelConfig = field(default_factory=ModelConfig)
    # training pairs are in the unit box, so PDSAC's inlier threshold is the auto value in those units
    pdsac: PDSACConfig = field(default_factory=lambda: PDSACConfig(num_hypotheses=64, temperature=0.01,
                                                                   inlier_threshold=0.05))
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossWeights = field(default_factory=LossWeights)
    gan: GanConfig = field(default_factory=GanConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    emd_epsilon: float = 0.01
    emd_iterations: int = 30
    emd_points: int | None = 256  # EMD terms on a random subset of this many points (None: all)
    checkpoint_every: int = 200
    validate_every: int = 500
    validation_pairs: int = 64
    log_every: int = 10


def load_train_config(path: str | Path, overrides: dict | None = None) -> TrainConfig:
    """Read a YAML training config; `overrides` (nested dict) win over the file."""
    values = yaml.safe_load(Path(path).read_text()) or {}
    for key, value in (overrides or {}).items():
        if isinstance(value, dict):
            values.setdefault(key, {}).update(value)
        else:
            values[key] = value
    return from_dict(TrainConfig, values)
