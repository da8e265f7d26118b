"""Discriminator for the adversarial loss (paper Sec. 3.4, appendix)."""

from __future__ import annotations

import torch
from torch import nn


class Discriminator(nn.Module):
    """Three fully connected layers with LeakyReLU: two per point (shared), max-pool over points, one
    to a single logit. Permutation invariant, so it judges the shape of a cloud, not its point order.
    Input (B, N, 3) centred clouds; output (B,) logits (real > 0).
    """

    def __init__(self, hidden: tuple[int, ...] = (64, 128)) -> None:
        super().__init__()
        self.point = nn.Sequential(
            nn.Linear(3, hidden[0]), nn.LeakyReLU(0.2), nn.Linear(hidden[0], hidden[1]), nn.LeakyReLU(0.2)
        )
        self.out = nn.Linear(hidden[1], 1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        centred = points - points.mean(dim=1, keepdim=True)
        return self.out(self.point(centred).amax(dim=1)).squeeze(-1)
