"""PDSAC: parallel and differentiable sample consensus (paper Sec. 3.3).

Given one-to-one correspondences src_i <-> dst_i (for GenReg: A_i <-> A_g,i), PDSAC draws m minimal
sets of k correspondences in one tensor operation, solves all m rigid transforms at once by SVD
(Kabsch, det R = +1), scores every hypothesis by its truncated projection error over all points,
    s_h = mean_i min(|R_h src_i + t_h - dst_i|, tau),
and keeps the best (hard argmin, inference). For training it also returns the soft, temperature
weighted selection w_h = softmax(-s_h / temperature) as in DSAC, so an expected loss
sum_h w_h loss(T_h) passes gradients to the correspondences.

Transforms are 4x4, column convention: dst ~ R src + t.

Overlap weighting (models with an overlap head): with per-correspondence weights o_i in (0, 1], the
minimal sets are drawn with probability proportional to o (without replacement within a set) and a
hypothesis scores s_h = sum_i o_i min(|R_h src_i + t_h - dst_i|, tau) / sum_i o_i, so correspondences
that likely have no counterpart neither seed nor vote for hypotheses.

Combining both directions (the paper's T_est = T_A^-1 T_B is written for row vectors and is
ambiguous). Column convention: A_g = T_A A maps A's frame into B's, and B_g = T_B B maps B's frame
into A's. Hence both T_A and T_B^-1 estimate T_BA, the transform from source A to target B, and the
union of correspondences {A_i -> A_g,i} and {B_g,i -> B_i} all obey B-frame = T_BA A-frame.
`pdsac_bidirectional` takes the `local_candidates` best hypotheses of each direction, refits each once on
its inliers in that union (local optimisation, as in LO-RANSAC), scores them on the union, keeps the best
and refits it by least squares on the union's inliers, then again at tighter thresholds
(`refit_tightening`: the loose threshold lets in matches a few samples off, which bias the fit): T_est =
T_BA, so that target ~ T_est source. The returned inliers are those within the inlier threshold.

Inference (`pdsac_bidirectional`, no gradient) runs both directions as one batch, and draws weighted
minimal sets by inverse CDF (`sample_weighted_sequential`): the distribution of the multinomial draws
`pdsac` makes in training (`sample_weighted_sets`), without drawing m x N exponentials. Training keeps
`pdsac` with its draws, so runs resume with identical numerics.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from genreg_core import kernels
from genreg_core.config import PDSACConfig
from genreg_core.geometry import apply_transform, invert_transform, kabsch


@dataclass
class PDSACResult:
    """Output of PDSAC for a batch of B correspondence sets."""

    transform: torch.Tensor  # (B, 4, 4) best hypothesis (refit on inliers when asked)
    hypotheses: torch.Tensor  # (B, m, 4, 4)
    scores: torch.Tensor  # (B, m) truncated mean projection error (lower is better)
    weights: torch.Tensor  # (B, m) soft selection, sums to 1
    inliers: torch.Tensor  # (B, N) bool, residual of `transform` below the threshold


# The minimal-set fits (`geometry.kabsch`: compiled at inference, batched SVDs in training) run on one thread
# whatever `torch.get_num_threads()` says, and release the GIL; with more than one torch thread (estimate_threads
# 0 or 2+) parts of the batch run on a small thread pool, with the same values (per-row work).
_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def _executor(size: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    if _pool is None or _pool_size < size:
        _pool, _pool_size = ThreadPoolExecutor(max_workers=size, thread_name_prefix="pdsac"), size
    return _pool


def _forget_pool() -> None:
    """A forked child has none of its parent's threads: it starts its own pool when it needs one."""
    global _pool, _pool_size
    _pool, _pool_size = None, 0


os.register_at_fork(after_in_child=_forget_pool)


def _without_grad(fn: Callable[..., torch.Tensor], *inputs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return fn(*inputs)


def batch_in_threads(fn: Callable[..., torch.Tensor], *inputs: torch.Tensor, dim: int = 0) -> torch.Tensor:
    """fn(*inputs), with the inputs split along `dim` into up to `torch.get_num_threads()` parts that run
    concurrently, the results concatenated along `dim`; fn must treat each index of `dim` on its own. Runs
    fn directly on one thread, on a single index, or when a gradient is recorded or autocast is on (both
    are thread-local state, which the pool's threads do not share)."""
    parts = min(torch.get_num_threads(), inputs[0].shape[dim])
    if parts < 2 or torch.is_grad_enabled() or torch.is_autocast_enabled(inputs[0].device.type):
        return fn(*inputs)
    chunks = list(zip(*(x.tensor_split(parts, dim=dim) for x in inputs), strict=True))
    pending = [_executor(parts - 1).submit(_without_grad, fn, *chunk) for chunk in chunks[1:]]
    return torch.cat([fn(*chunks[0]), *(p.result() for p in pending)], dim=dim)


def sample_minimal_sets(
    batch: int, num_points: int, m: int, k: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """(batch, m, k) indices, ascending in each set; each minimal set holds k distinct points, uniformly.

    Sequential draws without replacement: the j-th index is drawn from the N - j points not yet taken and
    mapped past the taken ones. O(m k^2), against a sort of m x N random keys.
    """
    picks = torch.empty(batch, m, 0, dtype=torch.long)
    for j in range(k):
        r = torch.randint(num_points - j, (batch, m, 1), generator=generator)
        for i in range(j):  # taken indices ascending: each one at or below r shifts r up by one
            r = r + (r >= picks[..., i : i + 1]).long()
        picks = torch.cat([picks, r], dim=-1).sort(dim=-1).values
    return picks


def sample_weighted_sets(weights: torch.Tensor, m: int, k: int, generator: torch.Generator | None = None
                         ) -> torch.Tensor:
    """(B, m, k) indices, ascending in each set, k distinct points per set drawn with probability
    proportional to `weights` (B, N) (successive draws without replacement)."""
    B = weights.shape[0]
    rows = weights.detach().clamp_min(1e-6).repeat_interleave(m, dim=0)  # (B m, N)
    return torch.multinomial(rows, k, replacement=False, generator=generator).reshape(B, m, k).sort(dim=-1).values


def sample_weighted_sequential(weights: torch.Tensor, m: int, k: int, generator: torch.Generator | None = None
                               ) -> torch.Tensor:
    """(B, m, k) indices, ascending in each set: k distinct points per set, drawn one after another with
    probability proportional to `weights` (B, N) among the points not yet taken (weights floored at 1e-6
    like `sample_weighted_sets`, whose distribution this is; different random draws).

    Inverse CDF on the cumulative weights: the j-th draw is uniform on the mass not yet taken and mapped
    past the taken points' intervals, as `sample_minimal_sets` maps past taken indices. O(m k^2 + m k log N)
    instead of m x N exponential draws (7 ms at m = N = 512, 1 CPU thread). Float64; a draw landing on a
    taken point's interval edge by rounding (~1e-13) would repeat a point, leaving a valid 3-point set.
    On the CPU the mapping runs compiled (`kernels.weighted_sets`) on the same uniform draws.
    """
    B, N = weights.shape
    w = weights.detach().to(torch.float64).clamp_min(1e-6)
    cdf = w.cumsum(dim=-1)  # point i owns [cdf_i - w_i, cdf_i)
    if kernels.usable(w):  # the same mapping of the same draws, compiled
        u = torch.stack([torch.rand(B, m, generator=generator, dtype=torch.float64) for _ in range(k)])
        return torch.from_numpy(kernels.weighted_sets(cdf.numpy(), w.numpy(), u.numpy()))
    starts = cdf - w
    picks = torch.empty(B, m, 0, dtype=torch.long, device=weights.device)
    left = cdf[:, -1:].expand(B, m)  # mass not yet taken, per set
    for _ in range(k):
        x = torch.rand(B, m, generator=generator, dtype=torch.float64, device=weights.device) * left
        for i in range(picks.shape[-1]):  # taken points ascending: skip the interval of each one at or below x
            taken = picks[..., i]
            x = x + (x >= starts.gather(1, taken)) * w.gather(1, taken)
        r = torch.searchsorted(cdf, x, right=True).clamp_max_(N - 1)
        left = left - w.gather(1, r)
        picks = torch.cat([picks, r[..., None]], dim=-1).sort(dim=-1).values
    return picks


def seeded_generator(seed: int | None) -> torch.Generator | None:
    """The random generator PDSAC draws from: seeded (deterministic), or None for fresh randomness."""
    return torch.Generator().manual_seed(seed) if seed is not None else None


def residuals(T: torch.Tensor, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """|R src_i + t - dst_i| for T (..., 4, 4), src/dst (B, N, 3) broadcast over hypothesis dims."""
    return torch.linalg.norm(apply_transform(T, src) - dst, dim=-1)


def hypothesis_residuals(T: torch.Tensor, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """|R_h src_i + t_h - dst_i| for m hypotheses T (B, m, 4, 4) and src/dst (B, N, 3) -> (B, m, N).

    Equal to `residuals(T, src[:, None], dst[:, None])`, as one matrix product of the stacked [R_h | t_h]
    (B, 3m, 4) with the homogeneous points (B, 4, N): 2.2 ms against 7.8 ms for the broadcast form at
    m = N = 512 on 2 CPU threads. Training's form; inference scores with `kernels.truncated_scores`.
    """
    B, m = T.shape[:2]
    homogeneous = torch.cat([src, torch.ones_like(src[..., :1])], dim=-1).transpose(1, 2)  # (B, 4, N)
    moved = (T[..., :3, :].reshape(B, 3 * m, 4) @ homogeneous).reshape(B, m, 3, -1)
    d = moved - dst.transpose(1, 2)[:, None]
    # three contiguous (B, m, N) planes: a norm over the middle axis is ~30x slower on CPU. The clamp
    # keeps the gradient finite (zero) at a zero residual, as torch.linalg.norm's is.
    return (d[:, :, 0].square() + d[:, :, 1].square() + d[:, :, 2].square()).clamp_min(1e-30).sqrt()


def pdsac(
    src: torch.Tensor,
    dst: torch.Tensor,
    cfg: PDSACConfig,
    generator: torch.Generator | None = None,
    refit: bool | None = None,
    weights: torch.Tensor | None = None,
    sets: torch.Tensor | None = None,
) -> PDSACResult:
    """Estimate dst ~ T src from (B, N, 3) correspondences, optionally weighted by per-correspondence
    overlap `weights` (B, N) (module docstring). Differentiable through the soft selection (and through
    `weights` in the scores). sets: (B, m, k) minimal sets to use instead of drawing them."""
    B, N, _ = src.shape
    if sets is not None:
        idx = sets
    elif weights is None:
        idx = sample_minimal_sets(B, N, cfg.num_hypotheses, cfg.sample_size, generator)
    else:
        idx = sample_weighted_sets(weights.cpu(), cfg.num_hypotheses, cfg.sample_size, generator)
    idx = idx.to(src.device)
    m, k = idx.shape[1:]
    flat = idx.reshape(B, -1, 1).expand(-1, -1, 3)
    s = torch.gather(src, 1, flat).reshape(B, m, k, 3)
    d = torch.gather(dst, 1, flat).reshape(B, m, k, 3)
    hyps = batch_in_threads(kabsch, s, d, dim=1)  # (B, m, 4, 4), the hypotheses in parts on 2+ threads
    if not kernels.usable(hyps, src, dst, weights):
        scores = truncated_score(hypothesis_residuals(hyps, src, dst), cfg.tau, weights)  # (B, m, N) -> (B, m)
    else:  # inference: compiled, without the (B, m, N) residual table
        rows = [x.transpose(1, 2).contiguous().numpy() for x in (src, dst)]
        w = (torch.ones(B, N, dtype=src.dtype) if weights is None else weights.to(src.dtype)).contiguous()
        scores = torch.from_numpy(kernels.truncated_scores(hyps.contiguous().numpy(), *rows, w.numpy(), cfg.tau))
    selection = torch.softmax(-scores / cfg.temperature, dim=-1)
    best = scores.argmin(dim=-1)
    T = hyps[torch.arange(B), best]
    inliers = residuals(T, src, dst) < cfg.tau
    if cfg.refit if refit is None else refit:
        T, inliers = refit_on_inliers(T, src, dst, cfg.tau)
    return PDSACResult(T, hyps, scores, selection, inliers)


def truncated_score(res: torch.Tensor, threshold: float, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean (or `weights`-weighted mean over the last axis) of residuals truncated at `threshold`:
    res (..., N), weights broadcasting as (B, 1.., N)."""
    truncated = res.clamp_max(threshold)
    if weights is None:
        return truncated.mean(dim=-1)
    w = weights.reshape(weights.shape[0], *([1] * (res.dim() - 2)), weights.shape[-1])
    return (truncated * w).sum(dim=-1) / w.sum(dim=-1).clamp_min(1e-9)


def refit_limits(threshold: float, rounds: int = 2, tightening: Sequence[float] = ()) -> tuple[float, ...]:
    """The inlier thresholds of `refit_on_inliers`' rounds, in order: `rounds` at `threshold`, then one at each
    `tightening` fraction of it."""
    return (threshold,) * rounds + tuple(threshold * f for f in tightening)


def refit_on_inliers(
    T: torch.Tensor, src: torch.Tensor, dst: torch.Tensor, threshold: float, rounds: int = 2,
    weights: torch.Tensor | None = None, tightening: Sequence[float] = (),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares re-estimate on the inliers of T (`rounds` rounds at `threshold`, then one at each
    `tightening` fraction of it; inliers weighted by `weights` (B, N) if given), keeping T where too few
    remain. Returns T and its inliers at `threshold`."""
    res = residuals(T, src, dst)
    for limit in refit_limits(threshold, rounds, tightening):
        inliers = res < limit
        enough = inliers.sum(dim=-1) >= 3
        w = inliers.to(src.dtype) if weights is None else inliers.to(src.dtype) * weights
        T = torch.where(enough[:, None, None], kabsch(src, dst, w), T)
        res = residuals(T, src, dst)
    return T, res < threshold


def union_correspondences(
    a: torch.Tensor, a_gen: torch.Tensor, b: torch.Tensor, b_gen: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """{A_i -> A_g,i} and {B_g,i -> B_i} as one set: (src (B, 2N, 3) in A's frame, dst in B's frame)."""
    return torch.cat([a, b_gen], dim=1), torch.cat([a_gen, b], dim=1)


def union_inlier_share(
    T: torch.Tensor, a: torch.Tensor, a_gen: torch.Tensor, b: torch.Tensor, b_gen: torch.Tensor, threshold: float
) -> torch.Tensor:
    """(B,) share of the union's correspondences that T (B, 4, 4), b ~ T a, maps within `threshold`."""
    src, dst = union_correspondences(a, a_gen, b, b_gen)
    return (residuals(T, src, dst) < threshold).to(src.dtype).mean(dim=-1)


def minimal_sets(points: torch.Tensor, cfg: PDSACConfig, generator: torch.Generator | None = None,
                 weights: torch.Tensor | None = None) -> torch.Tensor:
    """Inference draws for (B, N, 3) correspondences: (B, m, k) uniform minimal sets (as `pdsac` draws them),
    or weighted by `weights` (B, N) by `sample_weighted_sequential`."""
    B, N, _ = points.shape
    if weights is None:
        return sample_minimal_sets(B, N, cfg.num_hypotheses, cfg.sample_size, generator)
    return sample_weighted_sequential(weights.cpu(), cfg.num_hypotheses, cfg.sample_size, generator)


def split_result(res: PDSACResult, B: int) -> tuple[PDSACResult, PDSACResult]:
    """A result for a batch of 2B -> the results of its two halves."""
    halves = [t.split(B) for t in (res.transform, res.hypotheses, res.scores, res.weights, res.inliers)]
    return PDSACResult(*(h[0] for h in halves)), PDSACResult(*(h[1] for h in halves))


def best_hypotheses(res_a: PDSACResult, res_b: PDSACResult, n: int) -> torch.Tensor:
    """The n best-scoring hypotheses of each direction as transforms source A -> target B: (B, 2 n, 4, 4),
    A's (T_A) first, then B's inverted (T_B^-1)."""
    picks = []
    for res, invert in ((res_a, False), (res_b, True)):
        best = res.scores.topk(min(n, res.scores.shape[1]), dim=1, largest=False).indices  # (B, n)
        T = torch.gather(res.hypotheses, 1, best[..., None, None].expand(-1, -1, 4, 4))
        picks.append(invert_transform(T) if invert else T)
    return torch.cat(picks, dim=1)


def local_optimisation(candidates: torch.Tensor, src: torch.Tensor, dst: torch.Tensor, threshold: float,
                       weights: torch.Tensor | None = None) -> torch.Tensor:
    """Each candidate (B, C, 4, 4), dst ~ T src, refit once by least squares on its inliers among the (B, N, 3)
    correspondences (weighted by `weights` (B, N) if given), kept where fewer than 3 remain: a minimal set's
    fit carries its 3 points' noise, the refit averages it over all the inliers it found."""
    B, C = candidates.shape[:2]
    flat = candidates.reshape(B * C, 4, 4)
    rows = (src.repeat_interleave(C, dim=0), dst.repeat_interleave(C, dim=0))
    w = None if weights is None else weights.repeat_interleave(C, dim=0)
    return refit_on_inliers(flat, *rows, threshold, rounds=1, weights=w)[0].reshape(B, C, 4, 4)


@torch.no_grad()
def pdsac_bidirectional(
    a: torch.Tensor,
    a_gen: torch.Tensor,
    b: torch.Tensor,
    b_gen: torch.Tensor,
    cfg: PDSACConfig,
    generator: torch.Generator | None = None,
    overlap: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, PDSACResult, PDSACResult, torch.Tensor]:
    """One transform source A -> target B from both generated clouds (see module docstring), weighted
    by the overlap probabilities (o_A (B, N), o_B (B, M)) when given. Inference: no gradient (training
    uses `pdsac`); A's minimal sets are drawn first, then B's, and both directions run as one batch.

    Returns (T_est (B, 4, 4) with b ~ T_est a, result A->A_g, result B->B_g, union inlier mask (B, 2N)).
    """
    o_a, o_b = overlap if overlap is not None else (None, None)
    sets_a, sets_b = minimal_sets(a, cfg, generator, o_a), minimal_sets(b, cfg, generator, o_b)
    if a.shape == b.shape:
        both = pdsac(torch.cat([a, b]), torch.cat([a_gen, b_gen]), cfg, refit=False,
                     weights=None if overlap is None else torch.cat([o_a, o_b]), sets=torch.cat([sets_a, sets_b]))
        res_a, res_b = split_result(both, a.shape[0])
    else:
        res_a = pdsac(a, a_gen, cfg, refit=False, weights=o_a, sets=sets_a)
        res_b = pdsac(b, b_gen, cfg, refit=False, weights=o_b, sets=sets_b)
    src, dst = union_correspondences(a, a_gen, b, b_gen)
    w = None if overlap is None else torch.cat([o_a, o_b], dim=1)
    best = best_hypotheses(res_a, res_b, cfg.local_candidates)
    if kernels.usable(src, dst, w, best):  # the same steps, compiled
        limits = refit_limits(cfg.tau, tightening=cfg.refit_tightening) if cfg.refit else ()
        ones = torch.ones(src.shape[:2], dtype=src.dtype) if w is None else w.to(src.dtype)
        T, inliers = kernels.consensus(*(x.contiguous().numpy() for x in (best, src, dst, ones)), cfg.tau,
                                       np.asarray(limits, dtype=np.float64))
        return torch.from_numpy(T).to(src.dtype), res_a, res_b, torch.from_numpy(inliers)
    candidates = local_optimisation(best, src, dst, cfg.tau, w)
    score = truncated_score(residuals(candidates, src[:, None], dst[:, None]), cfg.tau, w)
    T = candidates[torch.arange(a.shape[0]), score.argmin(dim=1)]
    if cfg.refit:  # tightened last rounds: only the closest correspondences fit
        T, inliers = refit_on_inliers(T, src, dst, cfg.tau, weights=w, tightening=cfg.refit_tightening)
    else:
        inliers = residuals(T, src, dst) < cfg.tau
    return T, res_a, res_b, inliers


MODE_TRANSLATION = 0.1  # `distinct_modes`: translations this far apart (normalised frame: the unit box) differ


@torch.no_grad()
def both_directions(res_a: PDSACResult, res_b: PDSACResult) -> tuple[torch.Tensor, torch.Tensor]:
    """The hypotheses of both directions as transforms source A -> target B (B, 2m, 4, 4), A's first, then
    B's inverted, and their scores (B, 2m)."""
    return (torch.cat([res_a.hypotheses, invert_transform(res_b.hypotheses)], dim=1),
            torch.cat([res_a.scores, res_b.scores], dim=1))


def distinct_modes(T: torch.Tensor, hypotheses: torch.Tensor, scores: torch.Tensor, src: torch.Tensor,
                   dst: torch.Tensor, cfg: PDSACConfig, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Up to `cfg.modes` - 1 other modes among `hypotheses` (B, M, 4, 4), b ~ T a, with PDSAC `scores`
    (B, M; `both_directions`): in order of their scores, each hypothesis whose rotation differs by more than
    `cfg.mode_separation` deg, or
    its translation by more than `MODE_TRANSLATION`, from `T` (B, 4, 4) and every mode kept before it, refit
    on its inliers among the union correspondences `src`, `dst` (B, 2N, 3) as the winner is (`refit_on_inliers`
    with the tightening rounds). Slots without a distinct mode repeat `T`."""
    B, count = T.shape[0], cfg.modes - 1
    modes = T[:, None].repeat(1, max(count, 0), 1, 1)
    if count <= 0:
        return modes
    order = scores.argsort(dim=1)
    cos_limit = float(np.cos(np.radians(cfg.mode_separation)))
    for b in range(B):
        H = hypotheses[b, order[b]].to(T.dtype)
        kept = [T[b]]
        for _ in range(count):
            R, t = torch.stack(kept)[:, :3, :3], torch.stack(kept)[:, :3, 3]
            # cos of the angle between H's rotation and each kept one: (trace(R_k^T R_h) - 1) / 2
            cos = (torch.einsum("kij,hij->hk", R, H[:, :3, :3]) - 1) / 2
            near = (cos > cos_limit) & (torch.cdist(H[:, :3, 3], t) < MODE_TRANSLATION)
            far = ~near.any(dim=1)
            if not far.any():
                break
            kept.append(H[int(far.nonzero()[0])])
        if len(kept) > 1:
            fresh = torch.stack(kept[1:])
            rows = (src[b: b + 1].expand(len(fresh), -1, -1), dst[b: b + 1].expand(len(fresh), -1, -1))
            w = None if weights is None else weights[b: b + 1].expand(len(fresh), -1)
            modes[b, : len(fresh)] = refit_on_inliers(fresh, *rows, cfg.tau, weights=w,
                                                      tightening=cfg.refit_tightening)[0].to(T.dtype)
    return modes
