"""GenRegNet: the generator every shipped model uses (paper Fig. 2, with our measured levers).

Frames: A (source) and B (target) are (B, N, 3) clouds in their own frames (`genreg_core.geometry`).
The network generates A_g, point i of A expressed in B's frame, and B_g, point i of B expressed in A's
frame; PDSAC turns the pairs (A_i, A_g,i) and (B_g,i, B_i) into one transform. Three stages:

1. encode (paper Sec. 3.1): each cloud is centred on its centroid; a rotation-invariant point-pair-feature
   stem and an edge convolution (`invariant.InvariantEncoder`, in the GCNN's place) and the paper's two
   mixer layers (backbone "pointmixer"; "dgcnn": a linear layer instead) give per-point features F.
2. interact (the feature interaction, our soft pointer): each point of A attends to B's points by the
   cosine of learned, per-cloud-centred query/key features times a learned sharpness (and B to A).
3. generate: A_g,i is the best-matching point of B (hard pick; training passes gradients through the
   soft mean, straight-through), moved back by B's centroid; likewise B_g.

Because every input to the match is invariant, the generated correspondences do not depend on the
rotation between the clouds. A_g is always one of B's own sample points, so the estimate is as fine as
B's sampling (MODEL_CARD.md); the paper's decoder lives in `genreg_core.model.paper`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from genreg_core.config import ModelConfig
from genreg_core.model.invariant import InvariantEncoder
from genreg_core.model.layers import centroid, zero_last_layer
from genreg_core.model.mixer import MixerLayer


@dataclass
class GenRegOutput:
    """Generated clouds of one forward pass (both generator variants)."""

    source_generated: torch.Tensor  # A_g (B, N, 3), in B's frame
    target_generated: torch.Tensor  # B_g (B, N, 3), in A's frame
    # soft pointer only: log match weights, A's points onto B's (B, N, M) and B's onto A's (B, M, N)
    match_logits: tuple[torch.Tensor, torch.Tensor] | None = None


@dataclass
class Encoded:
    """Stage 1 output: centred clouds, their centroids and per-point features."""

    a0: torch.Tensor  # (B, N, 3) A - c_A
    b0: torch.Tensor  # (B, M, 3) B - c_B
    c_a: torch.Tensor  # (B, 1, 3)
    c_b: torch.Tensor
    f_a: torch.Tensor  # (B, N, C)
    f_b: torch.Tensor  # (B, M, C)


class PointMixerEncoder(nn.Module):
    """Invariant GCNN then two mixer layers (or one linear layer, backbone "dgcnn"):
    (B, N, 3) centred cloud -> (B, N, feature_dim)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.gcnn = InvariantEncoder(cfg.gcnn_channels, cfg.k_neighbors, norm=cfg.norm)
        if cfg.backbone == "dgcnn":
            self.mixer1: nn.Module = nn.Linear(cfg.gcnn_channels, cfg.feature_dim)
            self.mixer2: nn.Module = nn.Identity()
        else:
            h1, h2 = cfg.mixer_hidden
            self.mixer1 = MixerLayer(cfg.num_points, cfg.gcnn_channels, h1, cfg.feature_dim)
            self.mixer2 = MixerLayer(cfg.num_points, cfg.feature_dim, h2, cfg.feature_dim)
            for mixer in (self.mixer1, self.mixer2):  # token mixing starts as a no-op: point order is random
                zero_last_layer(mixer.token_mlp)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.mixer2(self.mixer1(self.gcnn(points)))


class SoftPointer(nn.Module):
    """Match logits of each point of x onto the points of y: cosine similarity of learned query/key
    features, each centred over its cloud, times a learned sharpness (starts at `sharpness`)."""

    def __init__(self, channels: int, dim: int, sharpness: float = 10.0) -> None:
        super().__init__()
        self.query = nn.Linear(channels, dim)
        self.key = nn.Linear(channels, dim)
        self.log_sharpness = nn.Parameter(torch.tensor(float(sharpness)).log())

    def forward(self, f_x: torch.Tensor, f_y: torch.Tensor) -> torch.Tensor:
        """(B, N, C), (B, M, C) features -> log weights (B, N, M), normalised over M."""
        q, k = self.query(f_x), self.key(f_y)
        # Centred over each cloud's points: the component all points share carries no match.
        q = nn.functional.normalize(q - q.mean(dim=1, keepdim=True), dim=-1)
        k = nn.functional.normalize(k - k.mean(dim=1, keepdim=True), dim=-1)
        return torch.log_softmax((q @ k.transpose(1, 2)) * self.log_sharpness.exp(), dim=-1)


def pick(log_w: torch.Tensor, y: torch.Tensor, straight_through: bool) -> torch.Tensor:
    """The best-matching point of y (B, M, 3) for each row of log_w (B, N, M): a real point, since a soft
    mean of several candidates lands between them, off the surface. With `straight_through` (training)
    gradients flow through the soft mean."""
    best = torch.gather(y, 1, log_w.argmax(dim=-1, keepdim=True).expand(-1, -1, 3))
    if not straight_through:
        return best
    soft = log_w.exp() @ y
    return best + (soft - soft.detach())


class GenRegNet(nn.Module):
    """The generator. `forward(a, b)` -> GenRegOutput. Inputs must hold exactly cfg.num_points points."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = cfg or ModelConfig()
        self.encoder = PointMixerEncoder(self.config)
        self.pointer = SoftPointer(self.config.feature_dim, self.config.attention_dim)

    def encode(self, a: torch.Tensor, b: torch.Tensor) -> Encoded:
        """Stage 1: centre both clouds, per-point invariant features (one batched pass for both)."""
        n = self.config.num_points
        if a.shape[1] != n or b.shape[1] != n:
            raise ValueError(f"GenRegNet expects {n} points, got {a.shape[1]} and {b.shape[1]}")
        c_a, c_b = centroid(a), centroid(b)
        a0, b0 = a - c_a, b - c_b
        f_a, f_b = self.encoder(torch.cat([a0, b0], dim=0)).chunk(2, dim=0)
        return Encoded(a0, b0, c_a, c_b, f_a, f_b)

    def interact(self, enc: Encoded) -> tuple[torch.Tensor, torch.Tensor]:
        """Stage 2: log match weights A -> B (B, N, M) and B -> A (B, M, N)."""
        return self.pointer(enc.f_a, enc.f_b), self.pointer(enc.f_b, enc.f_a)

    def generate(self, enc: Encoded, match: tuple[torch.Tensor, torch.Tensor]) -> GenRegOutput:
        """Stage 3: A_g (A in B's frame) and B_g (B in A's frame) from the matches."""
        log_w_a, log_w_b = match
        a_gen = pick(log_w_a, enc.b0, self.training) + enc.c_b
        b_gen = pick(log_w_b, enc.a0, self.training) + enc.c_a
        return GenRegOutput(a_gen, b_gen, match)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> GenRegOutput:
        enc = self.encode(a, b)
        return self.generate(enc, self.interact(enc))
