"""Statistics-free GenReg: fold fixed normalisation statistics into the layers before them.

GroupNorm normalises each point's features by statistics over all the points of its cloud, and the soft
pointer centres queries and keys on their cloud's mean: when a cloud is cropped these statistics move, so
the same surface point gets other features in a cropped source than in the target. With the statistics
fixed (averages over training clouds, `scripts/fold_norm.py`), GroupNorm(W x + b) is W' x + b' with
W' = s W, b' = s (b - mean) + beta, s = gamma / sqrt(var + eps) per channel; a positive s commutes with the
edge convolution's max over neighbours, so the edge convolution folds too. The centres fold into the
pointer's biases. The result is the same architecture with `norm: none` and `pointer_centring: false`:
with backbone "dgcnn", each point's features then depend on its two-hop neighbourhood alone.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from genreg_core.errors import CheckpointError
from genreg_core.model.genreg import GenRegNet


@dataclasses.dataclass
class NormStatistics:
    """Fixed statistics to fold: per GroupNorm (by module name) its per-group input mean and variance
    (num_groups,) each, and the soft pointer's query and key centres (attention_dim,)."""

    groups: dict[str, tuple[torch.Tensor, torch.Tensor]]
    query_centre: torch.Tensor
    key_centre: torch.Tensor


def fold_statistics(model: GenRegNet, stats: NormStatistics) -> GenRegNet:
    """A statistics-free copy of a GroupNorm, cloud-centred GenRegNet (eval mode): equal to `model` on any
    cloud whose statistics are `stats`. CheckpointError if the model is not of that kind or a GroupNorm
    scale is not positive (it would not commute with a max)."""
    cfg = model.config
    if not isinstance(model, GenRegNet) or cfg.norm != "group" or not cfg.pointer_centring:
        raise CheckpointError("fold_statistics needs a genreg model with GroupNorm and a cloud-centred pointer")
    modules = dict(model.named_modules())
    norms = {name for name, m in modules.items() if isinstance(m, nn.GroupNorm)}
    if norms != set(stats.groups):
        raise CheckpointError(f"statistics for {sorted(stats.groups)}, but the model normalises at {sorted(norms)}")
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    for name, (mean, var) in stats.groups.items():
        norm = modules[name]
        parent, _, child = name.rpartition(".")
        before = f"{parent}.{int(child) - 1}" if child.isdigit() else f"{parent}.linear"  # PointMLP / EdgeConv
        group = norm.num_channels // norm.num_groups
        mu, sd = mean.repeat_interleave(group), (var.repeat_interleave(group) + norm.eps).sqrt()
        scale = norm.weight.detach() / sd
        if (scale <= 0).any():
            raise CheckpointError(f"{name}: a non-positive scale does not commute with a max; cannot fold")
        w, b = state[f"{before}.weight"], state[f"{before}.bias"]
        state[f"{before}.weight"] = w * scale.view(-1, *([1] * (w.dim() - 1)))
        state[f"{before}.bias"] = scale * (b - mu) + norm.bias.detach()
        del state[f"{name}.weight"], state[f"{name}.bias"]
    state["pointer.query.bias"] -= stats.query_centre
    state["pointer.key.bias"] -= stats.key_centre
    folded = GenRegNet(dataclasses.replace(cfg, norm="none", pointer_centring=False))
    folded.load_state_dict(state)
    return folded.eval()


def widen(model: GenRegNet, gcnn_channels: int, feature_dim: int, seed: int = 0) -> GenRegNet:
    """A wider copy of a statistics-free "dgcnn" GenRegNet that computes the same function (Net2Net-style:
    each new channel gets random incoming weights and zero outgoing weights), the warm start for the
    widened partial-overlap model (MODEL_CARD.md). The edge convolution gets `gcnn_channels` outputs and the linear layer
    after it `feature_dim`; the PPF stem and the pointer's width stay. CheckpointError for other models or
    narrower widths."""
    cfg = model.config
    if not isinstance(model, GenRegNet) or cfg.backbone != "dgcnn" or cfg.norm != "none":
        raise CheckpointError("widen needs a statistics-free genreg model with backbone dgcnn")
    c0, f0 = cfg.gcnn_channels, cfg.feature_dim
    if gcnn_channels < c0 or feature_dim < f0:
        raise CheckpointError(f"widen cannot narrow: {c0}, {f0} -> {gcnn_channels}, {feature_dim}")
    wide = GenRegNet(dataclasses.replace(cfg, gcnn_channels=gcnn_channels, feature_dim=feature_dim))
    generator = torch.Generator().manual_seed(seed)
    old = {k: v.detach() for k, v in model.state_dict().items()}
    state = {k: v.clone() for k, v in old.items()}  # every tensor as it was, but those widened below

    def fresh(shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
        return torch.randn(shape, generator=generator) * like.std()

    ctx, mix = "encoder.gcnn.context.linear", "encoder.mixer1"
    w = old[f"{ctx}.weight"]  # (c0, 2 * 64): new output rows, random
    state[f"{ctx}.weight"] = torch.cat([w, fresh((gcnn_channels - c0, w.shape[1]), w)])
    state[f"{ctx}.bias"] = torch.cat([old[f"{ctx}.bias"], torch.zeros(gcnn_channels - c0)])
    w = old[f"{mix}.weight"]  # (f0, c0): new input columns zero, new output rows random
    top = torch.cat([w, torch.zeros(f0, gcnn_channels - c0)], dim=1)
    state[f"{mix}.weight"] = torch.cat([top, fresh((feature_dim - f0, gcnn_channels), w)])
    state[f"{mix}.bias"] = torch.cat([old[f"{mix}.bias"], torch.zeros(feature_dim - f0)])
    for name in ("pointer.query", "pointer.key", "overlap.mlp.0"):  # inputs [features, (extra)]: zero columns
        if f"{name}.weight" not in old:
            continue
        w = old[f"{name}.weight"]
        state[f"{name}.weight"] = torch.cat([w[:, :f0], torch.zeros(w.shape[0], feature_dim - f0), w[:, f0:]], dim=1)
    wide.load_state_dict(state)
    return wide.eval()
