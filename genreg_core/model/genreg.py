"""GenRegNet: the generator of GenReg (paper Fig. 2): T-Net, GCNN, two mixer layers, feature
interaction and decoder. The discriminator lives beside it and is used only in training.

Frames: A (source) and B (target) are (B, N, 3) clouds in their own frames. The network generates
A_g, point i of A expressed in B's frame, and B_g, point i of B expressed in A's frame.

Generation, column convention. With c_A, c_B the centroids (if `center_inputs`), R_pre the optional
PCA pre-rotation and T the T-Net transform, only A is moved, into B's centred frame (as in the paper,
the T-Net transforms one of the clouds):
    A_1 = T R_pre (A - c_A),   M = T [R_pre | 0]  (the network's centred estimate of A -> B),
so A_1 and B_0 = B - c_B share one frame, where the encoder, the feature interaction and the decoder
compare them. The decoder's per-point outputs d_A, d_B give
    A_g = A_1 + d_A + c_B            (A in B's frame; point i from point i)
    B_g = M^-1 (B_0 + d_B) + c_A     (B in A's frame).

The decoder sees [F_i, G_other - G_own, x_i] (the paper's feature interaction, `interaction="global"`).
Our levers, measured against it: `"local"` adds the offset from x_i to its nearest neighbour in the
other cloud and that neighbour's feature; `"attention"` (RPM-Net-like soft pointer) generates from
sum_j w_ij y_j, w_ij = softmax_j(q_i . k_j / sqrt(d) - |x_i - y_j|^2 / (2 sigma^2)), sigma learned.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from genreg_core.config import ModelConfig
from genreg_core.geometry import apply_transform, invert_transform
from genreg_core.model.decoder import Decoder
from genreg_core.model.discriminator import Discriminator
from genreg_core.model.gcnn import EdgeConv
from genreg_core.model.invariant import InvariantEncoder
from genreg_core.model.layers import centroid, zero_last_layer
from genreg_core.model.mixer import MixerLayer
from genreg_core.model.pointnet2 import PointNet2Encoder
from genreg_core.model.prealign import pca_prealign
from genreg_core.model.tnet import TNet


@dataclass
class GenRegOutput:
    """Generated clouds and the T-Net transforms of one forward pass."""

    source_generated: torch.Tensor  # A_g (B, N, 3), in B's frame
    target_generated: torch.Tensor  # B_g (B, N, 3), in A's frame
    tnet: torch.Tensor  # (B, 4, 4) T-Net transform of centred, pre-rotated A into B's centred frame
    prealign: torch.Tensor  # (B, 3, 3) pre-rotation of centred A (identity when off)
    # "attention" only: log pointer weights, A's points onto B's (B, N, M) and B's onto A's (B, M, N)
    match_logits: tuple[torch.Tensor, torch.Tensor] | None = None


class PointMixerEncoder(nn.Module):
    """GCNN (edge convolution on the kNN graph of the coordinates) then two mixer layers: (B, N, 3)
    -> (B, N, feature_dim)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.gcnn: nn.Module = (
            InvariantEncoder(cfg.gcnn_channels, cfg.k_neighbors, norm=cfg.norm) if cfg.encoder == "ppf"
            else EdgeConv(3, cfg.gcnn_channels, cfg.k_neighbors, norm=cfg.norm)
        )
        h1, h2 = cfg.mixer_hidden
        self.mixer1: nn.Module = MixerLayer(cfg.num_points, cfg.gcnn_channels, h1, cfg.feature_dim)
        self.mixer2: nn.Module = MixerLayer(cfg.num_points, cfg.feature_dim, h2, cfg.feature_dim)
        if cfg.backbone == "dgcnn":  # ablation "DGCNN only": a linear layer on the GCNN features
            self.mixer1, self.mixer2 = nn.Linear(cfg.gcnn_channels, cfg.feature_dim), nn.Identity()

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.mixer2(self.mixer1(self.gcnn(points)))


def build_encoder(cfg: ModelConfig) -> nn.Module:
    """The per-point feature extractor `cfg.backbone` names: (B, N, 3) -> (B, N, feature_dim)."""
    if cfg.backbone == "pointnet2":
        return PointNet2Encoder(cfg.feature_dim, cfg.k_neighbors, norm=cfg.norm)
    return PointMixerEncoder(cfg)


def nearest_neighbour_context(
    points: torch.Tensor, other: torch.Tensor, other_features: torch.Tensor
) -> torch.Tensor:
    """Local interaction: for each point, the offset to its nearest neighbour in the other cloud (both in
    the other cloud's centred frame) and that neighbour's feature. (B, N, 3), (B, M, 3), (B, M, C) ->
    (B, N, 3 + C). The neighbour index is not differentiated; the offset is."""
    with torch.no_grad():
        idx = torch.cdist(points, other).argmin(dim=-1)  # (B, N)
    nn_points = torch.gather(other, 1, idx[..., None].expand(-1, -1, 3))
    nn_features = torch.gather(other_features, 1, idx[..., None].expand(-1, -1, other_features.shape[-1]))
    return torch.cat([nn_points - points, nn_features], dim=-1)


class SoftPointer(nn.Module):
    """Attention of each point onto the other cloud's points (both in one frame): cosine similarity of
    learned query/key features (each centred over its cloud) times a learned sharpness (starts at
    `sharpness`), minus a Gaussian distance kernel of learned width (sigma 0: no kernel, features
    alone). Returns the best-matching point of the other cloud (gradients flow through the weighted
    mean, straight-through) and the log weights."""

    def __init__(self, channels: int, dim: int, sigma: float, sharpness: float = 10.0) -> None:
        super().__init__()
        self.query = nn.Linear(channels, dim)
        self.key = nn.Linear(channels, dim)
        self.spatial = sigma > 0
        self.log_sigma = nn.Parameter(torch.tensor(float(sigma if sigma > 0 else 1.0)).log())
        self.log_sharpness = nn.Parameter(torch.tensor(float(sharpness)).log())

    def forward(
        self, x: torch.Tensor, f_x: torch.Tensor, y: torch.Tensor, f_y: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """x (B, N, 3), y (B, M, 3) and their features -> (pointed points (B, N, 3), log weights (B, N, M))."""
        q, k = self.query(f_x), self.key(f_y)
        # Centred over each cloud's points: the component all points share carries no match.
        q = nn.functional.normalize(q - q.mean(dim=1, keepdim=True), dim=-1)
        k = nn.functional.normalize(k - k.mean(dim=1, keepdim=True), dim=-1)
        logits = (q @ k.transpose(1, 2)) * self.log_sharpness.exp()
        if self.spatial:
            logits = logits - torch.cdist(x, y).square() / (2.0 * self.log_sigma.exp().square())
        log_w = torch.log_softmax(logits, dim=-1)
        # The output is the best match itself, a real point of the other cloud: a soft mean of several
        # candidates lands between them, off the surface. Training passes gradients through the soft
        # mean (straight-through), so the decoder learns to refine the same points it sees at inference.
        best = torch.gather(y, 1, log_w.argmax(dim=-1, keepdim=True).expand(-1, -1, 3))
        if not self.training:
            return best, log_w
        soft = log_w.exp() @ y
        return best + (soft - soft.detach()), log_w


def feature_interaction(f_a: torch.Tensor, f_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """FI module: max-pool each cloud's features to G_A, G_B and append the difference of the other
    cloud's global feature and one's own to every point: [F_A, G_B - G_A] and [F_B, G_A - G_B]."""
    g_a, g_b = f_a.amax(dim=1, keepdim=True), f_b.amax(dim=1, keepdim=True)
    return (
        torch.cat([f_a, (g_b - g_a).expand_as(f_a)], dim=-1),
        torch.cat([f_b, (g_a - g_b).expand_as(f_b)], dim=-1),
    )


class GenRegNet(nn.Module):
    """The generator. `forward(a, b)` -> GenRegOutput. Inputs must hold exactly cfg.num_points points."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = cfg or ModelConfig()
        self.tnet = TNet(self.config) if self.config.tnet else None
        self.encoder = build_encoder(self.config)
        extra = {"global": 0, "local": 3 + self.config.feature_dim, "attention": 3}[self.config.interaction]
        self.decoder = Decoder(2 * self.config.feature_dim + 3 + extra, self.config.decoder_channels)
        if self.config.encoder == "ppf" and self.config.backbone == "pointmixer":  # token mixing starts as a no-op: random
            for mixer in (self.encoder.mixer1, self.encoder.mixer2):  # point order is not signal
                zero_last_layer(mixer.token_mlp)
        if self.config.interaction == "attention":
            self.pointer = SoftPointer(self.config.feature_dim, self.config.attention_dim, self.config.attention_sigma)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> GenRegOutput:
        cfg = self.config
        if a.shape[1] != cfg.num_points or b.shape[1] != cfg.num_points:
            raise ValueError(f"GenRegNet expects {cfg.num_points} points, got {a.shape[1]} and {b.shape[1]}")
        zero = torch.zeros_like(a[:, :1])
        c_a, c_b = (centroid(a), centroid(b)) if cfg.center_inputs else (zero, zero)
        a0, b0 = a - c_a, b - c_b
        R = torch.eye(3, dtype=a.dtype, device=a.device).expand(a.shape[0], 3, 3)
        if cfg.prealign == "pca":
            R = pca_prealign(a0, b0)
        a_pre = a0 @ R.transpose(1, 2)
        eye = torch.eye(4, dtype=a.dtype, device=a.device)
        T = self.tnet(a_pre, b0) if self.tnet is not None else eye.repeat(a.shape[0], 1, 1)
        a1 = apply_transform(T, a_pre)  # A in B's centred frame
        M = T.clone()
        M[:, :3, :3] = T[:, :3, :3] @ R
        f_a, f_b = self.encoder(torch.cat([a1, b0], dim=0)).chunk(2, dim=0)
        fused_a, fused_b = feature_interaction(f_a, f_b)
        inputs_a, inputs_b = [fused_a, a1], [fused_b, b0]
        base_a, base_b = a1, b0
        match = None
        if cfg.interaction == "local":
            inputs_a.append(nearest_neighbour_context(a1, b0, f_b))
            inputs_b.append(nearest_neighbour_context(b0, a1, f_a))
        elif cfg.interaction == "attention":
            (base_a, log_w_a), (base_b, log_w_b) = self.pointer(a1, f_a, b0, f_b), self.pointer(b0, f_b, a1, f_a)
            match = (log_w_a, log_w_b)
            inputs_a.append(base_a - a1)
            inputs_b.append(base_b - b0)
        if cfg.decoder_offsets:
            offsets = self.decoder(torch.cat([torch.cat(inputs_a, -1), torch.cat(inputs_b, -1)], 0))
        else:  # the pointer's picks are the generated points (measured better; MODEL_CARD.md)
            offsets = torch.zeros_like(torch.cat([a1, b0], 0))
        if cfg.offset_limit > 0:  # the decoder refines the pointer's output; it cannot undo it
            offsets = cfg.offset_limit * torch.tanh(offsets / cfg.offset_limit)
        d_a, d_b = offsets.chunk(2, dim=0)
        b_gen = apply_transform(invert_transform(M), base_b + d_b) + c_a
        return GenRegOutput(base_a + d_a + c_b, b_gen, T, R, match)


def build_discriminator(cfg: ModelConfig) -> Discriminator:
    return Discriminator(cfg.discriminator_hidden)
