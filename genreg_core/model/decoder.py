"""Decoder: four 1D convolutions with GELU between them (paper appendix)."""

from __future__ import annotations

import itertools

import torch
from torch import nn

from genreg_core.model.layers import zero_last_layer


class Decoder(nn.Module):
    """Per-point generator: (B, N, C) fused features -> (B, N, 3) offsets.

    Point i of the output is generated from point i of the input only (1x1 convolutions), which is
    the per-point correspondence PDSAC relies on. The last layer starts at zero.
    """

    def __init__(self, in_channels: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        chans = (in_channels, *hidden, 3)
        layers: list[nn.Module] = []
        for i, (c_in, c_out) in enumerate(itertools.pairwise(chans)):
            layers.append(nn.Conv1d(c_in, c_out, 1))
            if i < len(chans) - 2:
                layers.append(nn.GELU())
        self.net = nn.Sequential(*layers)
        zero_last_layer(self.net)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features.transpose(1, 2)).transpose(1, 2)
