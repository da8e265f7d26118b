"""Training and validation pair sets, and deterministic batching.

A batch is a pure function of (seed, iteration, rank), so resuming at an iteration replays exactly
the batches an uninterrupted run would have seen, with no data-loader state to save.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from genreg_core.data.modelnet40 import ModelNetPairs, balanced_sampler_indices, load_modelnet40
from genreg_core.training.config import TrainConfig


def build_pair_sets(cfg: TrainConfig) -> tuple[Any, Any]:
    """(training pairs, validation pairs). Validation is held out from training, never unseen data."""
    d = cfg.data
    n = cfg.model.num_points
    if d.dataset == "modelnet40":
        train = ModelNetPairs(
            load_modelnet40("train", "seen", d.root), num_points=n, variant=tuple(d.variants),
            max_angle_deg=d.max_angle_deg, max_translation=d.max_translation, seed=cfg.seed,
        )
        val = ModelNetPairs(
            load_modelnet40("test", "seen", d.root), num_points=n, variant=d.validation_variant,
            max_angle_deg=d.max_angle_deg, max_translation=d.max_translation, seed=cfg.seed + 1,
        )
        return train, val
    from genreg_core.training.scene_pairs import build_scene_pair_sets

    return build_scene_pair_sets(cfg)


def batch_indices(train_set: Any, cfg: TrainConfig, iteration: int, rank: int = 0) -> np.ndarray:
    rng = np.random.default_rng((cfg.seed, iteration, rank))
    labels = getattr(getattr(train_set, "shapes", None), "labels", None)
    if cfg.data.balanced and labels is not None:
        return balanced_sampler_indices(labels, cfg.schedule.batch_size, rng)
    return rng.choice(len(train_set), cfg.schedule.batch_size, replace=False)


def collate(items: list[dict]) -> dict[str, torch.Tensor]:
    """Stack the source, target and transform of pair dicts into float32 tensors."""
    return {
        key: torch.from_numpy(np.stack([np.asarray(it[key], dtype=np.float32) for it in items]))
        for key in ("source", "target", "transform")
    }


def make_batch(train_set: Any, cfg: TrainConfig, iteration: int, rank: int = 0) -> dict[str, torch.Tensor]:
    train_set.set_epoch(iteration)
    return collate([train_set[int(i)] for i in batch_indices(train_set, cfg, iteration, rank)])


def validation_batches(val_set: Any, count: int, batch_size: int) -> list[dict[str, torch.Tensor]]:
    """A fixed list of validation batches (first `count` items at epoch 0, spread over the set)."""
    val_set.set_epoch(0)
    idx = np.linspace(0, len(val_set) - 1, num=min(count, len(val_set))).astype(int)
    items = [val_set[int(i)] for i in idx]
    return [collate(items[i:i + batch_size]) for i in range(0, len(items), batch_size)]
