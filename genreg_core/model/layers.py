"""Small building blocks shared by the model parts."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from torch import nn


def norm_layer(kind: str, channels: int) -> nn.Module:
    """Normalisation for (B, C, N) point features: GroupNorm (batch-size independent) or none."""
    if kind == "group":
        return nn.GroupNorm(min(8, channels), channels)
    return nn.Identity()


class PointMLP(nn.Sequential):
    """Shared per-point MLP: Conv1d(kernel 1) -> norm -> activation per layer, on (B, C, N).

    Each 1x1 convolution runs as one batched matrix product (baddbmm) with the Conv1d's own parameters
    (checkpoints unchanged): on 2 CPU threads a 32 -> 64 layer on 2 x 10240 columns takes 3.2 ms this
    way against 9.7 ms through Conv1d (mkldnn), which made it the encoder's largest cost.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self:
            if isinstance(layer, nn.Conv1d):
                weight = layer.weight[..., 0].expand(x.shape[0], -1, -1)
                x = torch.baddbmm(layer.bias[None, :, None], weight, x)
            else:
                x = layer(x)
        return x


def point_mlp(channels: Sequence[int], norm: str = "none", activation: type[nn.Module] = nn.ReLU) -> PointMLP:
    """Shared per-point MLP on (B, C, N): conv -> norm -> activation per layer (see `PointMLP`)."""
    layers: list[nn.Module] = []
    for c_in, c_out in itertools.pairwise(channels):
        layers += [nn.Conv1d(c_in, c_out, 1), norm_layer(norm, c_out), activation()]
    return PointMLP(*layers)


def mlp(channels: Sequence[int], activation: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """Fully connected layers with an activation between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (c_in, c_out) in enumerate(itertools.pairwise(channels)):
        layers.append(nn.Linear(c_in, c_out))
        if i < len(channels) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


def zero_last_layer(module: nn.Module) -> None:
    """Zero the weights and bias of the last Linear/Conv1d so the module starts as a no-op."""
    last = [m for m in module.modules() if isinstance(m, (nn.Linear, nn.Conv1d))][-1]
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)


def centroid(points: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) -> (B, 1, 3) mean point."""
    return points.mean(dim=1, keepdim=True)
