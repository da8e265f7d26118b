"""Statistics-free GenReg: fold fixed normalisation statistics into the layers before them (issue 13).

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
