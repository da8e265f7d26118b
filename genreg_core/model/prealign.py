"""Classical PCA pre-alignment (a training lever, off in the paper's recipe).

Rotates a centred cloud a onto centred cloud b by matching principal axes. The four proper sign
choices of the axes plus the identity are scored by symmetric Chamfer distance, and the best one
wins, so the network only has to learn the residual rotation.
"""

from __future__ import annotations

import itertools

import torch

_SIGNS = [s for s in itertools.product((1.0, -1.0), repeat=3)]


@torch.no_grad()
def pca_prealign(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a, b: (B, N, 3) centred clouds. Returns R (B, 3, 3) with b ~ a R^T (column form: b ~ R a)."""
    _, Va = torch.linalg.eigh(a.transpose(1, 2) @ a)
    _, Vb = torch.linalg.eigh(b.transpose(1, 2) @ b)
    S = torch.tensor(_SIGNS, dtype=a.dtype, device=a.device)  # (8, 3)
    cand = Vb[:, None] @ torch.diag_embed(S)[None] @ Va.transpose(1, 2)[:, None]  # (B, 8, 3, 3)
    eye = torch.eye(3, dtype=a.dtype, device=a.device).expand(a.shape[0], 1, 3, 3)
    cand = torch.cat([eye, cand], dim=1)
    moved = a[:, None] @ cand.transpose(-1, -2)  # (B, 9, N, 3)
    d = torch.cdist(moved, b[:, None].expand_as(moved))
    score = d.amin(dim=-1).mean(-1) + d.amin(dim=-2).mean(-1)
    score = torch.where(torch.linalg.det(cand) > 0, score, torch.full_like(score, float("inf")))
    best = score.argmin(dim=1)
    return cand[torch.arange(a.shape[0]), best]
