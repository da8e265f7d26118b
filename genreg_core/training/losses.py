"""GenReg's training losses (paper Sec. 3.4), batched over (B, N, 3) clouds.

- absolute: EMD(A, B_g) + EMD(B, A_g)        (EMD by entropic optimal transport, `sinkhorn_emd`)
- relative: MAE of consecutive edge lengths |P_i - P_(i+1) mod N| between A, A_g and B, B_g
- cycle: EMD(F(G(A)), A) + EMD(F(G(B)), B)
- adversarial: discriminator real/fake (standard GAN or WGAN-GP)
- transformation: |T_est T_gt^-1 - I| (Frobenius), as DSAC's expectation over PDSAC's hypotheses
- correspondence (our lever, weight 0 in the paper's recipe): mean |A_g,i - T_gt A_i|
- matching (our lever, architecture "genreg" only): cross-entropy of the pointer's weights against
  the true soft match
- overlap (our lever, models with an overlap head): binary cross-entropy of the overlap logits against
  the true overlap (a counterpart within `overlap_radius` at the true pose)
Correspondence and matching terms count only points with a true counterpart (the overlap).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from genreg_core.geometry import invert_transform


def sinkhorn_emd(x: torch.Tensor, y: torch.Tensor, epsilon: float = 0.01, iterations: int = 50) -> torch.Tensor:
    """Approximate EMD between equal-size clouds: mean transported Euclidean distance under the
    entropic optimal plan (Sinkhorn, uniform marginals). (B, N, 3), (B, N, 3) -> (B,).

    Kernel form with each row shifted by its minimum cost (the shift cancels in the row scaling),
    so each iteration is two batched matrix-vector products. Smaller epsilon is closer to the exact
    EMD (`metrics.earth_movers_distance`) but needs more iterations; the plan is detached, so the
    gradient is that of the transport cost at the plan (envelope theorem).
    """
    cost = torch.cdist(x, y)  # (B, N, M)
    with torch.no_grad():
        kernel = torch.exp(-(cost - cost.amin(dim=-1, keepdim=True)) / epsilon)
        n, m = cost.shape[-2:]
        v = torch.full_like(cost[..., 0, :], 1.0 / m)
        for _ in range(iterations):
            u = (1.0 / n) / (kernel @ v[..., None])[..., 0].clamp_min(1e-30)
            v = (1.0 / m) / (kernel.transpose(-1, -2) @ u[..., None])[..., 0].clamp_min(1e-30)
        plan = u[..., :, None] * kernel * v[..., None, :]
    return (plan * cost).sum(dim=(-2, -1))


def random_subset(points: torch.Tensor, size: int | None, generator: torch.Generator | None = None) -> torch.Tensor:
    """The same random `size` point indices for every cloud of a (B, N, 3) batch (all if None)."""
    if size is None or size >= points.shape[1]:
        return points
    idx = torch.randperm(points.shape[1], generator=generator)[:size].to(points.device)
    return points[:, idx]


def edge_lengths(points: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """|P_i - P_(i+1) mod N| for (B, N, 3) -> (B, N). Smoothed by eps under the root: generated points
    can coincide (two points picking the same match), where the plain norm's gradient is 0/0 = NaN."""
    return ((points - points.roll(-1, dims=1)).square().sum(-1) + eps).sqrt()


def relative_loss(points: torch.Tensor, generated: torch.Tensor) -> torch.Tensor:
    """Mean absolute error of consecutive edge lengths, (B,)."""
    return (edge_lengths(points) - edge_lengths(generated)).abs().mean(dim=-1)


def transformation_error(T_est: torch.Tensor, T_gt: torch.Tensor) -> torch.Tensor:
    """|T_est T_gt^-1 - I|_F for T_est (..., 4, 4) broadcast against T_gt (B, 4, 4) -> (...)."""
    eye = torch.eye(4, dtype=T_est.dtype, device=T_est.device)
    return torch.linalg.norm(T_est @ invert_transform(T_gt) - eye, dim=(-2, -1))


def expected_transformation_loss(hypotheses: torch.Tensor, weights: torch.Tensor, T_gt: torch.Tensor) -> torch.Tensor:
    """DSAC: sum_h w_h |T_h T_gt^-1 - I| with hypotheses (B, m, 4, 4), weights (B, m) -> (B,)."""
    return (weights * transformation_error(hypotheses, T_gt[:, None])).sum(dim=-1)


def matching_loss(log_weights: torch.Tensor, moved: torch.Tensor, other: torch.Tensor, sigma: float,
                  mask: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy of a soft pointer's weights (B, N, M, log) against the true soft match: point i,
    moved into the other cloud's frame by the ground truth (`moved`, (B, N, 3)), should pick the
    points of `other` (B, M, 3) near it, p_ij ~ exp(-|moved_i - other_j|^2 / (2 sigma^2)). Averaged over
    the points where `mask` (B, N) holds (all if None). -> (B,)."""
    with torch.no_grad():
        target = torch.softmax(-torch.cdist(moved, other).square() / (2.0 * sigma**2), dim=-1)
    return masked_mean(-(target * log_weights).sum(-1), mask)


def masked_mean(values: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of (B, N) values over the last axis where `mask` holds (all if None); 0 where none does."""
    if mask is None:
        return values.mean(-1)
    m = mask.to(values.dtype)
    return (values * m).sum(-1) / m.sum(-1).clamp_min(1.0)


@torch.no_grad()
def overlap_labels(moved: torch.Tensor, other: torch.Tensor, radius: float) -> torch.Tensor:
    """(B, N) bool: point i, moved into the other cloud's frame by the ground truth, has a point of
    `other` (B, M, 3) within `radius`: it has a counterpart (the overlap)."""
    return torch.cdist(moved, other).amin(dim=-1) < radius


def gan_discriminator_loss(real_logits: torch.Tensor, fake_logits: torch.Tensor) -> torch.Tensor:
    """Standard GAN: -E[log D(real)] - E[log(1 - D(fake))]."""
    return F.binary_cross_entropy_with_logits(real_logits, torch.ones_like(real_logits)) + \
        F.binary_cross_entropy_with_logits(fake_logits, torch.zeros_like(fake_logits))


def gan_generator_loss(fake_logits: torch.Tensor) -> torch.Tensor:
    """Non-saturating generator loss -E[log D(G(x))]."""
    return F.binary_cross_entropy_with_logits(fake_logits, torch.ones_like(fake_logits))


def wgan_gradient_penalty(discriminator: torch.nn.Module, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """WGAN-GP: E[(|grad D(x_hat)| - 1)^2] on random interpolates of real and fake clouds."""
    alpha = torch.rand(real.shape[0], 1, 1, dtype=real.dtype, device=real.device)
    x_hat = (alpha * real + (1 - alpha) * fake).requires_grad_(True)
    (grad,) = torch.autograd.grad(discriminator(x_hat).sum(), x_hat, create_graph=True)
    return ((grad.flatten(1).norm(dim=1) - 1.0) ** 2).mean()
