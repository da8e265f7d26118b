"""Scene-model pairs from 7-Scenes redkitchen: FMR-style pairs and real frame pairs (i, i+g).

Frames 0-799 train, 800-999 validate (the last 20 % of the sequence). Unseen scenes (stairs, SUN3D)
are never used here. All pairs are in unit-box units (the source fills [0, 1]^3).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from genreg_core.data.rgbd import (
    REDKITCHEN_TRAIN_FRAMES,
    REDKITCHEN_VAL_FRAMES,
    FMRPairs,
    FramePairs,
    RGBDSequence,
)
from genreg_core.training.config import TrainConfig

PIXEL_STRIDE = 2  # 320 x 240 back-projected pixels per frame: plenty for N <= 2048 and 4x faster


class MixedPairs:
    """Concatenation of pair sets behind one index; `set_epoch` and `max_angle_deg` reach every part
    that has them (the curriculum applies to the synthetic FMR pairs only)."""

    def __init__(self, parts: list[Any]) -> None:
        self.parts = parts
        self.offsets = np.cumsum([0] + [len(p) for p in parts])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, index: int) -> dict:
        k = int(np.searchsorted(self.offsets, index, side="right") - 1)
        return self.parts[k][index - int(self.offsets[k])]

    def set_epoch(self, epoch: int) -> None:
        for p in self.parts:
            p.set_epoch(epoch)

    @property
    def max_angle_deg(self) -> float:
        return max(getattr(p, "max_angle_deg", 0.0) for p in self.parts)

    @max_angle_deg.setter
    def max_angle_deg(self, value: float) -> None:
        for p in self.parts:
            if hasattr(p, "max_angle_deg"):
                p.max_angle_deg = value


def _pairs(cfg: TrainConfig, frames: range, seed: int, gaps: tuple[int, ...], kidnap: bool) -> MixedPairs:
    d, n = cfg.data, cfg.model.num_points
    seq = RGBDSequence.redkitchen(d.root)
    parts: list[Any] = []
    if "fmr" in d.pair_modes:
        parts.append(FMRPairs(seq, frames, num_points=n, seed=seed, max_angle_deg=d.max_angle_deg,
                              max_translation=d.max_translation, stride=PIXEL_STRIDE))
    if "frames" in d.pair_modes:
        parts += [FramePairs(seq, g, frames, num_points=n, seed=seed, normalize=True, stride=PIXEL_STRIDE,
                             kidnap=kidnap) for g in gaps]
    return MixedPairs(parts)


def build_scene_pair_sets(cfg: TrainConfig) -> tuple[MixedPairs, MixedPairs]:
    """(training pairs from frames 0-799, validation pairs from frames 800-999)."""
    d = cfg.data
    train = _pairs(cfg, REDKITCHEN_TRAIN_FRAMES, cfg.seed, tuple(d.frame_gaps), d.frame_kidnap)
    val = _pairs(cfg, REDKITCHEN_VAL_FRAMES, cfg.seed + 1, (d.validation_frame_gap,), d.frame_kidnap)
    return train, val
