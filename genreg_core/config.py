"""Typed configuration of genreg_core. Every default lives here, once.

Dataclasses load from plain dicts (YAML) with `from_dict`, which rejects unknown keys and wrong
types with a `ConfigError` naming the field.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from genreg_core.errors import ConfigError

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA_ROOT = REPO_ROOT.parent / "shared" / "data"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


def data_root(configured: str | os.PathLike | None = None) -> Path:
    """Dataset folder: `GENREG_DATA` if set, else `configured`, else ../shared/data beside the repo."""
    env = os.environ.get("GENREG_DATA")
    return Path(env or configured or DEFAULT_DATA_ROOT).expanduser()


@dataclass(frozen=True)
class ModelConfig:
    """Network architecture (paper Sec. 3 and appendix). Stored inside every checkpoint."""

    num_points: int = 512  # N: token mixing fixes it; the API resamples inputs to N
    k_neighbors: int = 20  # GCNN kNN graph size
    tnet_channels: tuple[int, ...] = (64, 128, 1024)  # T-Net shared point MLP
    tnet_head: tuple[int, ...] = (512, 256)  # T-Net MLP on both global features, then 6
    gcnn_channels: int = 64  # edge-convolution output channels
    mixer_hidden: tuple[int, ...] = (1024, 128)  # hidden width of mixer layer 1 and 2 (token and channel MLPs)
    feature_dim: int = 128  # per-point feature after the mixers
    decoder_channels: tuple[int, ...] = (256, 128, 64)  # three hidden 1D convs, a fourth outputs xyz
    discriminator_hidden: tuple[int, ...] = (64, 128)  # per-point FCs, max-pool, then FC -> 1
    center_inputs: bool = True  # subtract each cloud's centroid before the network
    prealign: str = "none"  # "none" or "pca": classical PCA pre-rotation, the net learns the residual
    norm: str = "group"  # normalisation in the point MLPs: "none" or "group"
    interaction: str = "global"  # "global": the paper's FI; "local": + nearest neighbour; "attention": soft pointer
    attention_dim: int = 64  # query/key width of the "attention" interaction
    attention_sigma: float = 0.05  # initial width of its distance kernel, unit-box units (learned); 0: no kernel
    encoder: str = "xyz"  # "xyz": the paper's GCNN on coordinates; "ppf": rotation-invariant point-pair features
    offset_limit: float = 0.0  # decoder offsets squashed to |d| < this (L tanh(d / L)); 0: unbounded
    backbone: str = "pointmixer"  # "pointmixer": GCNN + the paper's two mixer layers; ablations: "dgcnn"
    # (GCNN features alone, then a linear layer), "pointnet2" (PointNet++-style set abstraction and feature
    # propagation on the same invariant inputs; needs encoder "ppf")
    decoder_offsets: bool = True  # False ("attention" only): A_g is the pointer's pick, the decoder idles
    tnet: bool = True  # the paper's T-Net; off: identity (an invariant encoder does not need it)

    def __post_init__(self) -> None:
        _check(self.num_points >= 32, "model.num_points must be >= 32")
        _check(1 <= self.k_neighbors < self.num_points, "model.k_neighbors must be in [1, num_points)")
        _check(len(self.mixer_hidden) == 2, "model.mixer_hidden needs two widths (one per mixer layer)")
        _check(len(self.decoder_channels) == 3, "model.decoder_channels needs three widths")
        _check(self.prealign in ("none", "pca"), "model.prealign must be 'none' or 'pca'")
        _check(self.norm in ("none", "group"), "model.norm must be 'none' or 'group'")
        _check(self.encoder in ("xyz", "ppf"), "model.encoder must be 'xyz' or 'ppf'")
        _check(self.backbone in ("pointmixer", "dgcnn", "pointnet2"),
               "model.backbone must be 'pointmixer', 'dgcnn' or 'pointnet2'")
        _check(self.backbone != "pointnet2" or self.encoder == "ppf", "model.backbone 'pointnet2' needs encoder 'ppf'")
        _check(self.decoder_offsets or self.interaction == "attention",
               "model.decoder_offsets: false needs interaction 'attention' (the pointer generates the points)")
        _check(self.offset_limit >= 0, "model.offset_limit must be >= 0")
        _check(self.attention_sigma >= 0, "model.attention_sigma must be >= 0")
        _check(self.interaction in ("global", "local", "attention"),
               "model.interaction must be 'global', 'local' or 'attention'")


@dataclass(frozen=True)
class PDSACConfig:
    """Parallel differentiable sample consensus (paper Sec. 3.3)."""

    num_hypotheses: int = 512  # m minimal sets drawn at once (50 % outliers: P(no clean set) ~ 1e-14)
    sample_size: int = 4  # k correspondences per minimal set
    inlier_threshold: float = 0.05  # residual cut-off in unit-box units (score truncation, inliers)
    temperature: float = 0.01  # softmax temperature of the soft (training) selection
    refit: bool = True  # least-squares refit on the winner's inliers (inference)

    def __post_init__(self) -> None:
        _check(self.num_hypotheses >= 1, "pdsac.num_hypotheses must be >= 1")
        _check(self.sample_size >= 3, "pdsac.sample_size must be >= 3")
        _check(self.inlier_threshold > 0, "pdsac.inlier_threshold must be > 0")
        _check(self.temperature > 0, "pdsac.temperature must be > 0")


@dataclass(frozen=True)
class RefineConfig:
    """Optional ICP refinement after GenReg + PDSAC (Open3D)."""

    method: str = "none"  # "none", "point_to_point" or "point_to_plane"
    max_iterations: int = 10
    max_correspondence_distance: float = 0.05  # unit-box units (the source's bounding box is 1)
    num_points: int = 5000  # points per cloud for ICP and the fitness measure
    # Guard against a wrong global estimate (e.g. a symmetric shape flipped): when the confidence after
    # refinement is below `guard_below`, ICP also runs from the initial guess (identity if none), with the
    # wide cut-off `guard_distance` and `guard_iterations`; the start whose result overlaps the target
    # better (fitness) wins. 0 turns the guard off. Chosen on training-split pairs (MODEL_CARD.md).
    guard_below: float = 0.4
    guard_distance: float = 0.5  # unit-box units: ICP from the initial guess, as a skilled user runs it
    guard_iterations: int = 50

    def __post_init__(self) -> None:
        _check(
            self.method in ("none", "point_to_point", "point_to_plane"),
            "refine.method must be 'none', 'point_to_point' or 'point_to_plane'",
        )
        _check(self.max_iterations >= 1, "refine.max_iterations must be >= 1")
        _check(self.max_correspondence_distance > 0, "refine.max_correspondence_distance must be > 0")
        _check(self.num_points >= 16, "refine.num_points must be >= 16")
        _check(0.0 <= self.guard_below <= 1.0, "refine.guard_below must be in [0, 1]")
        _check(self.guard_distance > 0, "refine.guard_distance must be > 0")
        _check(self.guard_iterations >= 1, "refine.guard_iterations must be >= 1")


@dataclass(frozen=True)
class RegistrationConfig:
    """Everything the registration API needs besides the network weights."""

    pdsac: PDSACConfig = field(default_factory=PDSACConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    passes: int = 1  # network + PDSAC passes; pass k registers the residual left by pass k-1
    min_points: int = 32  # fewer finite points than this raises TooFewPointsError
    seed: int | None = 0  # subsampling and hypothesis seed; None draws fresh randomness
    device: str = "cpu"

    def __post_init__(self) -> None:
        _check(self.min_points >= 4, "min_points must be >= 4")
        _check(self.passes >= 1, "passes must be >= 1")


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


T = TypeVar("T")


def from_dict(cls: type[T], values: dict[str, Any] | None) -> T:
    """Build dataclass `cls` from a dict: unknown keys and wrong types raise ConfigError."""
    values = dict(values or {})
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"{cls.__name__}: unknown key(s) {unknown}; allowed: {sorted(names)}")
    kwargs = {name: _coerce(cls.__name__, name, hints[name], value) for name, value in values.items()}
    return cls(**kwargs)


def _coerce(owner: str, name: str, hint: Any, value: Any) -> Any:
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(f"{owner}.{name} must be a mapping, got {type(value).__name__}")
        return from_dict(hint, value)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        hint = next(a for a in args if a is not type(None))
        origin = typing.get_origin(hint)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{owner}.{name} must be a list, got {type(value).__name__}")
        item = typing.get_args(hint)[0]
        return tuple(_coerce(owner, name, item, v) for v in value)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and not (
        isinstance(value, hint) and not (hint is not bool and isinstance(value, bool))
    ):
        raise ConfigError(f"{owner}.{name} must be {hint.__name__}, got {value!r}")
    return value
