"""T-Net: pose normalisation by a learned rigid transform (paper Sec. 3.1 and appendix)."""

from __future__ import annotations

import torch
from torch import nn

from genreg_core.config import ModelConfig
from genreg_core.geometry import apply_transform, params_to_transform
from genreg_core.model.layers import mlp, point_mlp, zero_last_layer


class TNet(nn.Module):
    """Shared point MLP [64, 128, 1024] + max-pool on each cloud; an MLP [512, 256, 6] on the
    concatenated global features regresses 3 rotation (axis-angle) + 3 translation parameters.

    `forward(a, b)` returns (T_a, T_b), each (B, 4, 4): T_a is regressed from [g_a, g_b] and moves
    cloud a towards cloud b's pose; T_b from [g_b, g_a] moves b towards a. The last layer starts at
    zero, so an untrained T-Net is the identity.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.features = point_mlp((3, *cfg.tnet_channels), norm=cfg.norm)
        self.head = mlp((2 * cfg.tnet_channels[-1], *cfg.tnet_head, 6))
        zero_last_layer(self.head)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        both = torch.cat([a, b], dim=0).transpose(1, 2)  # (2B, 3, N): one pass for both clouds
        g_a, g_b = self.features(both).amax(dim=2).chunk(2, dim=0)
        params = self.head(torch.cat([torch.cat([g_a, g_b], 1), torch.cat([g_b, g_a], 1)], 0))
        T_a, T_b = params_to_transform(params).chunk(2, dim=0)
        return T_a, T_b

    @staticmethod
    def apply(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        return apply_transform(T, points)
