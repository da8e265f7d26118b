"""Mixer layers of PointMixer (paper Sec. 3.1, appendix): token mixing, then channel mixing."""

from __future__ import annotations

import torch
from torch import nn


class MixerLayer(nn.Module):
    """One mixer layer on (B, N, C) point features.

    Token mixing: an MLP of two fully connected layers across the point axis (N -> hidden -> N),
    residual. Channel mixing: an MLP of two layers across channels (C -> hidden -> C_out), with a
    linear skip when C != C_out. LayerNorm before each MLP and GELU inside it, as in MLP-Mixer.
    Token mixing ties the layer to a fixed N.
    """

    def __init__(self, num_points: int, in_channels: int, hidden: int, out_channels: int) -> None:
        super().__init__()
        self.token_norm = nn.LayerNorm(in_channels)
        self.token_mlp = nn.Sequential(nn.Linear(num_points, hidden), nn.GELU(), nn.Linear(hidden, num_points))
        self.channel_norm = nn.LayerNorm(in_channels)
        self.channel_mlp = nn.Sequential(
            nn.Linear(in_channels, hidden), nn.GELU(), nn.Linear(hidden, out_channels)
        )
        self.skip = nn.Identity() if in_channels == out_channels else nn.Linear(in_channels, out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.token_mlp(self.token_norm(x).transpose(1, 2)).transpose(1, 2)
        return self.skip(x) + self.channel_mlp(self.channel_norm(x))
