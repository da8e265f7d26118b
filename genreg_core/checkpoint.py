"""Checkpoint files of the generator: save (fp16 storage) and load (weights_only=True).

A checkpoint is a dict {"format", "model_config", "state_dict", "meta"} of plain Python values and
tensors, so `torch.load(weights_only=True)` reads it. A bare name (e.g. "modelnet40") means the
shipped file genreg_core/weights/<name>.pt.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch
from torch import nn

from genreg_core.config import WEIGHTS_DIR, ModelConfig, from_dict
from genreg_core.errors import CheckpointError, ConfigError
from genreg_core.model import build_model

FORMAT = "genreg-checkpoint-v1"


def resolve_checkpoint(name_or_path: str | os.PathLike) -> Path:
    """A path as given, or a shipped checkpoint by name. Raises CheckpointError if it does not exist."""
    text = str(name_or_path)
    path = Path(text).expanduser()
    if not path.suffix and os.sep not in text:
        path = WEIGHTS_DIR / f"{text}.pt"
    if path.is_dir():
        raise CheckpointError(f"checkpoint {path} is a directory, not a checkpoint file")
    if not path.is_file():
        shipped = sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt"))
        raise CheckpointError(f"checkpoint not found: {path} (shipped models: {shipped or 'none'})")
    return path


def _unreadable(path: Path, exc: Exception) -> str:
    """One line on why torch could not read a checkpoint file, without torch's advice to unpickle it
    unsafely (`weights_only=False` would run whatever code the file holds)."""
    if path.stat().st_size == 0:
        return f"checkpoint {path} is empty (0 bytes)"
    text = str(exc)
    if not zipfile.is_zipfile(path):  # torch writes zip archives; a cut-off one loses its directory at the end
        return f"checkpoint {path} is truncated or not a torch checkpoint ({path.stat().st_size} bytes)"
    if isinstance(exc, pickle.UnpicklingError) or "weights_only" in text:
        return (f"checkpoint {path} holds objects other than tensors and plain values; refused, since loading "
                "them could run code (a genreg checkpoint holds only weights and settings)")
    first = (text.strip().splitlines() or [type(exc).__name__])[0]
    return f"checkpoint {path} is corrupt or not a genreg checkpoint: {first}"


def save_checkpoint(
    model: nn.Module, path: str | os.PathLike, meta: dict[str, Any] | None = None, half: bool = True
) -> Path:
    """Write the generator's weights (fp16 when `half`) and its ModelConfig."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: (v.detach().half() if half and v.is_floating_point() else v.detach()).cpu().contiguous()
             for k, v in model.state_dict().items()}
    config = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(model.config).items()}
    torch.save({"format": FORMAT, "model_config": config, "state_dict": state, "meta": meta or {}}, path)
    return path


def any_size(cfg: ModelConfig) -> bool:
    """Whether a model runs at any N with the same weights (no token mixing: backbone "dgcnn")."""
    return cfg.backbone == "dgcnn" and cfg.architecture == "genreg"


def resized(model: nn.Module, num_points: int) -> nn.Module | None:
    """The same generator (its weights copied) for clouds of `num_points` points, in eval mode on its
    device; None when it runs at one N only (`any_size`)."""
    cfg = model.config
    if cfg.num_points == num_points:
        return model
    if not any_size(cfg):
        return None
    other = build_model(dataclasses.replace(cfg, num_points=num_points))
    other.load_state_dict(model.state_dict())
    return other.to(next(model.parameters()).device).eval()


def load_checkpoint(
    name_or_path: str | os.PathLike, num_points: int | None = None, device: str = "cpu"
) -> tuple[nn.Module, dict[str, Any]]:
    """Load a generator in eval mode (float32). `num_points`, if given, must match the model's N, except for
    backbone "dgcnn", which runs at any N."""
    path = resolve_checkpoint(name_or_path)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - pickle, zip and unpickler errors all mean: unusable
        raise CheckpointError(_unreadable(path, exc)) from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path} is not in format {FORMAT}")
    try:
        cfg = from_dict(ModelConfig, blob["model_config"])
    except (ConfigError, KeyError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path} has an invalid model config: {exc}") from None
    if num_points is not None and cfg.num_points != num_points and any_size(cfg):
        cfg = dataclasses.replace(cfg, num_points=num_points)
    if num_points is not None and cfg.num_points != num_points:
        raise CheckpointError(
            f"checkpoint {path} was built for N={cfg.num_points} points, but N={num_points} was requested"
        )
    model = build_model(cfg)
    try:
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in blob["state_dict"].items()})
    except (RuntimeError, KeyError, AttributeError) as exc:
        raise CheckpointError(f"checkpoint {path} does not fit the model it describes: {exc}") from None
    return model.to(device).eval(), dict(blob.get("meta", {}))
