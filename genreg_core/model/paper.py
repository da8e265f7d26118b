"""The paper's own generator (GenReg, Fig. 2 and appendix), kept as a tested variant for ablations.

`ModelConfig(architecture="paper")` builds it; no shipped model uses it (MODEL_CARD.md, "History": on 2
CPU cores it never learned rotation past 14 deg). Same three stages as `genreg_core.model.genreg`:

1. encode: each cloud is centred; a T-Net regresses a rigid transform T that moves centred A into B's
   centred frame, A_1 = T (A - c_A); an edge convolution on the coordinates (GCNN) and the two mixer
   layers give per-point features.
2. interact: the feature interaction (FI): max-pool each cloud's features to G_A, G_B and append the
   difference of the other cloud's global feature and one's own: [F_A, G_B - G_A], [F_B, G_A - G_B].
3. generate: a decoder of four 1x1 convolutions turns [FI_i, x_i] into per-point offsets d:
   A_g = A_1 + d_A + c_B (A in B's frame), B_g = T^-1 (B_0 + d_B) + c_A (B in A's frame).

Layer widths are the paper's (appendix) and fixed here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from genreg_core.config import ModelConfig
from genreg_core.geometry import apply_transform, invert_transform
from genreg_core.model.decoder import Decoder
from genreg_core.model.gcnn import EdgeConv
from genreg_core.model.genreg import GenRegOutput
from genreg_core.model.layers import centroid
from genreg_core.model.mixer import MixerLayer
from genreg_core.model.tnet import TNet

TNET_CHANNELS = (64, 128, 1024)  # T-Net shared point MLP
TNET_HEAD = (512, 256)  # T-Net MLP on both global features, then 6 pose parameters
DECODER_CHANNELS = (256, 128, 64)  # three hidden 1x1 convolutions; a fourth outputs xyz


@dataclass
class PaperEncoded:
    """Stage 1 output: A moved into B's centred frame, B centred, the T-Net transform, centroids, features."""

    a1: torch.Tensor
    b0: torch.Tensor
    T: torch.Tensor  # (B, 4, 4): centred A -> B's centred frame
    c_a: torch.Tensor
    c_b: torch.Tensor
    f_a: torch.Tensor
    f_b: torch.Tensor


class PaperGenRegNet(nn.Module):
    """The paper's generator: `forward(a, b)` -> GenRegOutput (no match logits)."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = cfg or ModelConfig(architecture="paper")
        c = self.config
        self.tnet = TNet(TNET_CHANNELS, TNET_HEAD, norm=c.norm)
        self.gcnn = EdgeConv(3, c.gcnn_channels, c.k_neighbors, norm=c.norm)
        h1, h2 = c.mixer_hidden
        self.mixer1 = MixerLayer(c.num_points, c.gcnn_channels, h1, c.feature_dim)
        self.mixer2 = MixerLayer(c.num_points, c.feature_dim, h2, c.feature_dim)
        self.decoder = Decoder(2 * c.feature_dim + 3, DECODER_CHANNELS)

    def encode(self, a: torch.Tensor, b: torch.Tensor) -> PaperEncoded:
        c_a, c_b = centroid(a), centroid(b)
        a0, b0 = a - c_a, b - c_b
        T = self.tnet(a0, b0)
        a1 = apply_transform(T, a0)
        f_a, f_b = self.mixer2(self.mixer1(self.gcnn(torch.cat([a1, b0], dim=0)))).chunk(2, dim=0)
        return PaperEncoded(a1, b0, T, c_a, c_b, f_a, f_b)

    def interact(self, enc: PaperEncoded) -> tuple[torch.Tensor, torch.Tensor]:
        g_a, g_b = enc.f_a.amax(dim=1, keepdim=True), enc.f_b.amax(dim=1, keepdim=True)
        return (torch.cat([enc.f_a, (g_b - g_a).expand_as(enc.f_a)], dim=-1),
                torch.cat([enc.f_b, (g_a - g_b).expand_as(enc.f_b)], dim=-1))

    def generate(self, enc: PaperEncoded, fused: tuple[torch.Tensor, torch.Tensor]) -> GenRegOutput:
        inputs = torch.cat([torch.cat([fused[0], enc.a1], -1), torch.cat([fused[1], enc.b0], -1)], dim=0)
        d_a, d_b = self.decoder(inputs).chunk(2, dim=0)
        b_gen = apply_transform(invert_transform(enc.T), enc.b0 + d_b) + enc.c_a
        return GenRegOutput(enc.a1 + d_a + enc.c_b, b_gen)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> GenRegOutput:
        enc = self.encode(a, b)
        return self.generate(enc, self.interact(enc))
