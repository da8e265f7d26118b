"""T-Net: pose normalisation by a learned rigid transform (paper Sec. 3.1 and appendix)."""

from __future__ import annotations

import torch
from torch import nn

from genreg_core.geometry import params_to_transform
from genreg_core.model.layers import mlp, point_mlp, zero_last_layer


class TNet(nn.Module):
    """Shared point MLP [64, 128, 1024] + max-pool on each cloud; an MLP [512, 256, 6] on the
    concatenated global features [g_a, g_b] regresses 3 rotation (axis-angle) + 3 translation
    parameters of the rigid transform that moves cloud a towards cloud b's pose. As in the paper, the
    T-Net transforms one of the two clouds. The last layer starts at zero: an untrained T-Net is the
    identity. `forward(a, b)` -> (B, 4, 4).
    """

    def __init__(self, channels: tuple[int, ...], head: tuple[int, ...], norm: str = "group") -> None:
        super().__init__()
        self.features = point_mlp((3, *channels), norm=norm)
        self.head = mlp((2 * channels[-1], *head, 6))
        zero_last_layer(self.head)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        both = torch.cat([a, b], dim=0).transpose(1, 2)  # (2B, 3, N): one pass for both clouds
        g_a, g_b = self.features(both).amax(dim=2).chunk(2, dim=0)
        return params_to_transform(self.head(torch.cat([g_a, g_b], dim=1)))
