"""PointNet++-style encoder (backbone ablation, `ModelConfig.backbone = "pointnet2"`).

Qi et al.'s segmentation layout on the same rotation-invariant inputs as the PPF encoder, so that the
ablation compares aggregation, not invariance:

1. set abstraction at every point: the PPF stem (point-pair features of each point with its k nearest
   neighbours, shared MLP, max-pool; `invariant.PPFStem`) -> f1 (B, N, 64);
2. set abstraction on N / `ratio` centres chosen by farthest point sampling: each centre groups its
   `coarse_k` nearest points, a shared MLP sees [PPF(centre, neighbour), f1 of the neighbour], max-pool
   -> f2 (B, M, 128);
3. feature propagation: f2 interpolated back to every point from its 3 nearest centres (inverse-
   distance weights), concatenated with f1, shared MLP -> (B, N, out_channels).

Every input to the MLPs is a distance or an unsigned angle, and sampling starts from the point
farthest from the centroid, so the features do not change when the (centred) cloud rotates.
"""

from __future__ import annotations

import torch
from torch import nn

from genreg_core.model.gcnn import knn_query
from genreg_core.model.invariant import PPFStem, gather_neighbours, point_pair_features
from genreg_core.model.layers import point_mlp


@torch.no_grad()
def farthest_point_sample(points: torch.Tensor, m: int) -> torch.Tensor:
    """Indices (B, m) of m points of (B, N, 3) centred clouds by farthest point sampling, started at
    the point farthest from the origin (deterministic, invariant to rotation and point order)."""
    B = points.shape[0]
    rows = torch.arange(B, device=points.device)
    chosen = torch.empty(B, m, dtype=torch.long, device=points.device)
    nearest = torch.full(points.shape[:2], float("inf"), dtype=points.dtype, device=points.device)
    far = points.square().sum(-1).argmax(-1)
    for i in range(m):
        chosen[:, i] = far
        nearest = torch.minimum(nearest, (points - points[rows, far][:, None]).square().sum(-1))
        far = nearest.argmax(-1)
    return chosen


class PointNet2Encoder(PPFStem):
    """(B, N, 3) centred cloud -> (B, N, out_channels) by set abstraction at two scales and feature
    propagation (module doc)."""

    def __init__(
        self, out_channels: int, k: int, norm: str = "group", ratio: int = 4, coarse_k: int = 32
    ) -> None:
        super().__init__(k, norm)
        self.ratio, self.coarse_k = ratio, coarse_k
        self.abstraction = point_mlp((4 + 64, 128, 128), norm=norm)
        self.propagation = point_mlp((128 + 64, 128), norm=norm)
        self.head = nn.Conv1d(128, out_channels, 1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        f1, _, normals = self.stem(points)
        B, N, _ = points.shape
        centres_idx = farthest_point_sample(points, max(1, N // self.ratio))
        centres = gather_neighbours(points, centres_idx[..., None])[:, :, 0]
        centre_normals = gather_neighbours(normals, centres_idx[..., None])[:, :, 0]
        _, group = knn_query(centres, points, min(self.coarse_k, N))  # (B, M, k)
        ppf = self.scaled(point_pair_features(
            centres, centre_normals, gather_neighbours(points, group), gather_neighbours(normals, group)
        ))
        grouped = torch.cat([ppf, gather_neighbours(f1, group)], dim=-1)  # (B, M, k, 68)
        M, k = group.shape[1:]
        f2 = self.abstraction(grouped.reshape(B, M * k, -1).transpose(1, 2)).reshape(B, -1, M, k).amax(-1)
        dist, nearest = knn_query(points, centres, min(3, M))  # (B, N, 3)
        weights = 1.0 / dist.clamp_min(1e-8)
        weights = weights / weights.sum(-1, keepdim=True)
        up = (gather_neighbours(f2.transpose(1, 2), nearest) * weights[..., None]).sum(2)  # (B, N, 128)
        h = self.propagation(torch.cat([up, f1], dim=-1).transpose(1, 2))
        return self.head(h).transpose(1, 2)
