"""Inference fast paths against their reference forms: the model's no-gradient paths give the values
of the differentiable ones, PDSAC's batched inference equals its per-direction form, and its weighted sampler
draws from the same distribution as the multinomial one training uses. Nothing here is timed."""

import itertools

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from scipy.stats import chisquare
from torch import nn

from genreg_core import kernels
from genreg_core.config import ModelConfig, PDSACConfig
from genreg_core.geometry import apply_transform, invert_transform, kabsch, random_transform
from genreg_core.model.gcnn import knn_indices, neighbour_max
from genreg_core.model.genreg import GenRegNet, neighbour_mix, row_max
from genreg_core.model.invariant import invariant_geometry, smallest_eigenpair3
from genreg_core.model.layers import gather_neighbours, per_cloud, point_mlp
from genreg_core.pdsac import (
    batch_in_threads,
    hypothesis_residuals,
    pdsac,
    pdsac_bidirectional,
    sample_weighted_sequential,
    sample_weighted_sets,
    truncated_score,
)

SMALL = ModelConfig(num_points=64, k_neighbors=8, gcnn_channels=16, mixer_hidden=(32, 16), feature_dim=16)
PARTIAL = ModelConfig(**{**SMALL.__dict__, "backbone": "dgcnn", "point_feature": "knn", "generation": "neighbours",
                         "generation_k": 6, "overlap_head": True})


def _reference_gather(values: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    B, M, k = neighbours.shape
    flat = neighbours.reshape(B, M * k, 1).expand(-1, -1, values.shape[-1])
    return torch.gather(values, 1, flat).reshape(B, M, k, -1)


def test_gather_neighbours_equals_torch_gather_with_and_without_gradient():
    torch.manual_seed(0)
    values = torch.randn(3, 50, 7)
    neighbours = torch.randint(0, 50, (3, 40, 9))[..., ::2]  # a non-contiguous index too
    with torch.no_grad():
        assert torch.equal(gather_neighbours(values, neighbours), _reference_gather(values, neighbours))
    values.requires_grad_(True)
    (grad,) = torch.autograd.grad(gather_neighbours(values, neighbours).square().sum(), values)
    (expected,) = torch.autograd.grad(_reference_gather(values, neighbours).square().sum(), values)
    assert torch.equal(grad, expected)  # training's path is torch.gather's, gradient included


def test_point_mlp_in_place_path_equals_the_differentiable_one_and_relu_commutes_with_the_max():
    torch.manual_seed(0)
    mlp = point_mlp((4, 32, 64), norm="group")
    for m in mlp.modules():
        if isinstance(m, nn.GroupNorm):
            nn.init.normal_(m.weight)
            nn.init.normal_(m.bias)
    x = torch.randn(2, 4, 300)
    reference = mlp(x)  # gradient enabled: baddbmm, out-of-place activations
    with torch.no_grad():
        assert torch.allclose(mlp(x), reference, atol=1e-6)
        assert torch.equal(x, x.clone())  # the input is left alone
        pre = mlp.forward_inplace(x, last_activation=False)
        assert torch.allclose(pre.relu(), reference, atol=1e-6)
        assert torch.equal(pre.reshape(2, 64, 30, 10).amax(-1).relu(), pre.relu().reshape(2, 64, 30, 10).amax(-1))


def test_per_cloud_equals_the_batched_computation():
    torch.manual_seed(0)
    net = GenRegNet(SMALL).eval()
    x = torch.rand(3, 64, 3)
    x = x - x.mean(1, keepdim=True)
    nb = knn_indices(x, 8)
    stem = net.encoder.gcnn
    edge = torch.rand(3, 64, 8, 4)
    p = torch.randn(3, 64, 16)
    with torch.no_grad():
        assert torch.allclose(per_cloud(stem.edge_max, edge), stem.edge_mlp(edge.reshape(3, -1, 4).transpose(1, 2))
                              .reshape(3, -1, 64, 8).amax(-1), atol=1e-6)
        assert torch.equal(per_cloud(neighbour_max, p, nb), _reference_gather(p, nb).amax(2))


@pytest.mark.parametrize("cfg", [SMALL, PARTIAL], ids=["pointmixer-pick", "dgcnn-neighbours-overlap"])
def test_inference_forward_equals_the_differentiable_forward(cfg: ModelConfig):
    """Eval mode: the no-gradient forward (index_select gathers, in-place MLPs, one cloud at a time, the
    encoder's kNN graph reused for neighbour generation) gives the gradient-enabled forward's outputs."""
    torch.manual_seed(0)
    net = GenRegNet(cfg).eval()
    for m in net.modules():
        if isinstance(m, (nn.GroupNorm, nn.LayerNorm)):
            nn.init.normal_(m.weight, 1.0, 0.3)
            nn.init.normal_(m.bias, 0.0, 0.3)
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    reference = net(a, b)
    with torch.no_grad():
        fast = net(a, b)
    for name in ("source_generated", "target_generated"):
        assert torch.allclose(getattr(fast, name), getattr(reference, name), atol=1e-5)
    for x, y in zip(fast.match_logits, reference.match_logits, strict=True):  # log weights of size ~10, summed
        assert torch.allclose(x, y, atol=1e-4)  # in other orders (row products, in place): float32 rounding
    if cfg.overlap_head:
        for x, y in zip(fast.overlap_logits, reference.overlap_logits, strict=True):
            assert torch.allclose(x, y, atol=1e-5)


def test_neighbour_mix_from_the_encoder_graph_equals_a_fresh_query_and_the_torch_form():
    """With the encoder's graph, inference mixes in one compiled pass (`kernels.neighbour_mix`): the torch
    form's values (a fresh kNN query, gathers and a softmax) to float32 rounding, and an explicit
    weighted mean of the best match's 6 nearest neighbours."""
    torch.manual_seed(0)
    y = torch.rand(2, 80, 3)
    log_w = torch.log_softmax(3 * torch.randn(2, 70, 80), dim=-1)
    best = log_w.argmax(-1)
    graph = knn_indices(y, 20)
    fast = neighbour_mix(log_w, best, y, 6, graph)
    assert kernels.usable(log_w, y)
    assert torch.allclose(fast, neighbour_mix(log_w, best, y, 6), atol=1e-6)
    near = torch.cdist(y[1, best[1, 9]][None], y[1]).argsort()[0, :6]  # the pick's 6 nearest (itself first)
    w = torch.softmax(log_w[1, 9, near], dim=0)
    assert torch.allclose(fast[1, 9], (w[:, None] * y[1, near]).sum(0), atol=1e-6)


def test_match_best_is_the_argmax_of_the_match_weights():
    torch.manual_seed(0)
    net = GenRegNet(PARTIAL).eval()
    with torch.no_grad():
        match = net.interact(net.encode(torch.rand(1, 64, 3), torch.rand(1, 64, 3)))
    assert torch.equal(match.best_a, match.log_w_a.argmax(-1)) and torch.equal(match.best_b, match.log_w_b.argmax(-1))


def test_compiled_row_max_is_torchs_indexed_max_ties_included():
    """`genreg.row_max` (compiled where usable): torch's value and first index of each row's maximum, on
    log weights with exact ties planted (the lower index wins, as torch's max)."""
    torch.manual_seed(0)
    x = torch.log_softmax(5 * torch.randn(3, 200, 130), dim=-1)
    top = x.amax(dim=-1, keepdim=True)
    x[:, ::3, 77] = top[:, ::3, 0]  # a tie after the first maximum
    x[:, 1::3, 5] = top[:, 1::3, 0]  # a tie before it
    x[:, 2::3, :] = -1.5  # a row of equal values
    with torch.no_grad():
        value, index = row_max(x)
    expected = x.max(dim=-1)
    assert kernels.usable(x) and torch.equal(value, expected.values) and torch.equal(index, expected.indices)
    assert (index[:, 2::3] == 0).all()


def _set_probabilities(w: np.ndarray, k: int) -> dict[tuple[int, ...], float]:
    """Exact probability of each k-set under successive draws without replacement, proportional to w."""
    probs = {}
    for subset in itertools.combinations(range(len(w)), k):
        total = 0.0
        for order in itertools.permutations(subset):
            left, p = w.sum(), 1.0
            for i in order:
                p, left = p * w[i] / left, left - w[i]
            total += p
        probs[subset] = total
    return probs


@pytest.mark.parametrize("sampler", [sample_weighted_sequential, sample_weighted_sets])
def test_weighted_samplers_draw_distinct_sets_with_the_successive_draw_probabilities(sampler):
    w = torch.tensor([[0.5, 3.0, 1.0, 0.05, 2.0, 1.5], [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]], dtype=torch.float64)
    sets = sampler(w, 40000, 3, torch.Generator().manual_seed(3))
    assert sets.shape == (2, 40000, 3) and (sets[..., 1:] > sets[..., :-1]).all()
    for row in range(2):
        probs = _set_probabilities(w[row].numpy(), 3)
        observed = np.array([(sets[row].numpy() == np.array(s)).all(1).sum() for s in probs])
        assert chisquare(observed, np.array(list(probs.values())) * observed.sum()).pvalue > 1e-3


def test_sequential_sampler_is_seeded_and_skips_points_without_weight():
    weights = torch.full((1, 300), 1e-9)
    weights[0, 100:140] = 1.0
    first = sample_weighted_sequential(weights, 500, 4, torch.Generator().manual_seed(1))
    again = sample_weighted_sequential(weights, 500, 4, torch.Generator().manual_seed(1))
    assert torch.equal(first, again)
    assert (first[..., 1:] > first[..., :-1]).all() and (first >= 100).all() and (first < 140).all()


def test_compiled_scores_equal_the_residual_table_form_training_uses():
    rng = np.random.default_rng(0)
    T = torch.tensor(np.stack([[random_transform(rng) for _ in range(150)] for _ in range(2)]), dtype=torch.float32)
    src, dst, w = torch.rand(2, 90, 3), torch.rand(2, 90, 3), torch.rand(2, 90)
    expected = torch.linalg.norm(apply_transform(T, src[:, None]) - dst[:, None], dim=-1)  # broadcast form
    assert torch.allclose(hypothesis_residuals(T, src, dst), expected, atol=1e-5)
    for weights in (None, w):
        table = truncated_score(expected, 0.3, weights)
        ones = torch.ones(2, 90) if weights is None else weights
        compiled = kernels.truncated_scores(T.numpy(), src.transpose(1, 2).contiguous().numpy(),
                                            dst.transpose(1, 2).contiguous().numpy(), ones.numpy(), 0.3)
        assert torch.allclose(torch.from_numpy(compiled), table, atol=1e-6)
    sets = torch.sort(torch.rand(2, 64, 90).argsort(-1)[..., :3], dim=-1).values  # the same minimal sets
    cfg = PDSACConfig(num_hypotheses=64, inlier_threshold=0.3)
    with torch.no_grad():
        fast = pdsac(src, dst, cfg, refit=False, weights=w, sets=sets)
    slow = pdsac(src.requires_grad_(), dst, cfg, refit=False, weights=w, sets=sets)  # training's path
    assert torch.allclose(fast.hypotheses, slow.hypotheses.detach(), atol=1e-4)
    assert torch.allclose(fast.scores, slow.scores.detach(), atol=1e-5)


@pytest.mark.parametrize("k", [3, 4, 60])
def test_compiled_kabsch_equals_the_svd_form_and_recovers_exact_motions(k: int):
    rng = np.random.default_rng(k)
    R = torch.tensor(Rotation.random(400, random_state=k).as_matrix())
    src = torch.tensor(rng.random((400, k, 3)))
    exact = src @ R.transpose(1, 2) + torch.tensor(rng.normal(size=(400, 1, 3)))
    noisy = exact + 0.05 * torch.tensor(rng.normal(size=(400, k, 3)))
    w = torch.tensor(rng.random((400, k)))
    with torch.no_grad():
        assert torch.allclose(kabsch(src, exact)[:, :3, :3], R, atol=1e-7)  # the truth, in float64
        compiled = kabsch(src, noisy, w)
    svd = kabsch(src.clone().requires_grad_(), noisy, w).detach()  # the differentiable SVD form
    assert torch.allclose(compiled, svd, atol=1e-6)
    assert torch.allclose(torch.linalg.det(compiled[:, :3, :3]), torch.ones(400, dtype=torch.float64))
    with torch.no_grad():  # no weight at all: identity
        assert torch.equal(kabsch(src[:2], noisy[:2], torch.zeros(2, k, dtype=torch.float64)),
                           torch.eye(4, dtype=torch.float64).expand(2, 4, 4))


def test_compiled_consensus_equals_pdsacs_torch_steps(monkeypatch: pytest.MonkeyPatch):
    """pdsac_bidirectional's local optimisation, candidate choice and tightened refits in compiled code give the
    transform and inliers of the torch steps (with the SVD fits) on noisy, outlier-ridden correspondences."""
    rng = np.random.default_rng(5)
    T = torch.tensor(np.stack([random_transform(rng) for _ in range(3)]), dtype=torch.float32)
    a, b = torch.rand(3, 256, 3), torch.rand(3, 256, 3)
    a_gen = apply_transform(T, a) + 0.01 * torch.randn(3, 256, 3)
    b_gen = apply_transform(invert_transform(T), b) + 0.01 * torch.randn(3, 256, 3)
    a_gen[:, :80], b_gen[:, 100:160] = torch.rand(3, 80, 3), torch.rand(3, 60, 3)  # outliers
    overlap = (torch.rand(3, 256), torch.rand(3, 256))
    cfg = PDSACConfig(inlier_threshold=0.05)
    compiled = pdsac_bidirectional(a, a_gen, b, b_gen, cfg, torch.Generator().manual_seed(0), overlap)
    monkeypatch.setattr(kernels, "usable", lambda *tensors: False)
    reference = pdsac_bidirectional(a, a_gen, b, b_gen, cfg, torch.Generator().manual_seed(0), overlap)
    assert torch.allclose(compiled[0], reference[0], atol=1e-4) and torch.equal(compiled[3], reference[3])
    assert torch.allclose(compiled[0], T, atol=0.02)  # and both found the motion


def test_compiled_weighted_sets_equal_the_torch_mapping_of_the_same_draws(monkeypatch: pytest.MonkeyPatch):
    weights = torch.rand(2, 700)
    weights[:, 300:500] = 1e-9  # floored at 1e-6: still drawable, rarely
    compiled = sample_weighted_sequential(weights, 512, 4, torch.Generator().manual_seed(3))
    monkeypatch.setattr(kernels, "usable", lambda *tensors: False)
    assert torch.equal(compiled, sample_weighted_sequential(weights, 512, 4, torch.Generator().manual_seed(3)))


def test_compiled_invariant_geometry_equals_the_torch_form(monkeypatch: pytest.MonkeyPatch):
    torch.manual_seed(0)
    points = torch.rand(2, 256, 3) - 0.5
    graph = knn_indices(points, 20)
    compiled = invariant_geometry(points, graph)
    monkeypatch.setattr(kernels, "usable", lambda *tensors: False)
    edge, point, normals = invariant_geometry(points, graph)
    assert torch.allclose(compiled[0], edge, atol=1e-5) and torch.allclose(compiled[1], point, atol=1e-6)
    assert ((compiled[2] * normals).sum(-1).abs() > 1 - 1e-5).all()  # unoriented: the same line


def test_batch_in_threads_gives_the_direct_values():
    torch.manual_seed(0)
    s, d = torch.rand(2, 301, 4, 3), torch.rand(2, 301, 4, 3)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with torch.no_grad():
            assert torch.equal(batch_in_threads(kabsch, s, d, dim=1), kabsch(s, d))
            assert torch.equal(batch_in_threads(kabsch, s[:1], d[:1], dim=0), kabsch(s[:1], d[:1]))  # one part
    finally:
        torch.set_num_threads(threads)


def _noisy_pair(seed: int, n: int = 300, outliers: float = 0.3):
    rng = np.random.default_rng(seed)
    T = torch.tensor(random_transform(rng))[None]
    a = torch.tensor(rng.random((1, n, 3)))
    b = torch.tensor(rng.random((1, n, 3)))
    a_gen, b_gen = apply_transform(T, a), apply_transform(invert_transform(T), b)
    bad = rng.random(n) < outliers
    a_gen[0, bad] = torch.tensor(rng.uniform(-1, 2, (int(bad.sum()), 3)))
    return T, a, a_gen, b, b_gen, torch.tensor(~bad)[None]


def test_bidirectional_batched_pass_equals_per_direction_pdsac_on_the_same_sets():
    T, a, a_gen, b, b_gen, good = _noisy_pair(0)
    cfg = PDSACConfig(num_hypotheses=200)
    o_a = torch.where(good, 0.9, 0.05).double()
    o_b = torch.full_like(o_a, 0.5)
    T_est, res_a, res_b, inliers = pdsac_bidirectional(a, a_gen, b, b_gen, cfg, torch.Generator().manual_seed(2),
                                                       (o_a, o_b))
    gen = torch.Generator().manual_seed(2)  # the same draws: A's sets first, then B's
    sets_a = sample_weighted_sequential(o_a, 200, cfg.sample_size, gen)
    sets_b = sample_weighted_sequential(o_b, 200, cfg.sample_size, gen)
    single_a = pdsac(a, a_gen, cfg, refit=False, weights=o_a, sets=sets_a)
    single_b = pdsac(b, b_gen, cfg, refit=False, weights=o_b, sets=sets_b)
    for res, single in ((res_a, single_a), (res_b, single_b)):
        assert torch.allclose(res.hypotheses, single.hypotheses, atol=1e-12)
        assert torch.allclose(res.scores, single.scores, atol=1e-12)
        assert torch.equal(res.transform, single.transform)
    assert torch.allclose(T_est, T, atol=1e-6) and inliers.shape == (1, 600)


def test_overlap_weighted_bidirectional_recovers_the_motion_past_a_majority_of_outliers():
    """75 % of A's correspondences agree on a wrong motion; with overlap weights marking the true ones,
    the inference path (sequential weighted draws) recovers the true motion."""
    rng = np.random.default_rng(4)
    a, b = torch.tensor(rng.random((1, 200, 3))), torch.tensor(rng.random((1, 200, 3)))
    T_true, T_wrong = (torch.tensor(random_transform(rng, 40, 0.3))[None] for _ in range(2))
    a_gen, b_gen = apply_transform(T_wrong, a), apply_transform(invert_transform(T_wrong), b)
    a_gen[:, :50] = apply_transform(T_true, a[:, :50])
    b_gen[:, :50] = apply_transform(invert_transform(T_true), b[:, :50])
    weights = torch.full((1, 200), 1e-6, dtype=torch.float64)
    weights[:, :50] = 1.0
    cfg = PDSACConfig(num_hypotheses=64)
    T_est, *_ = pdsac_bidirectional(a, a_gen, b, b_gen, cfg, torch.Generator().manual_seed(0), (weights, weights))
    assert torch.allclose(T_est, T_true, atol=1e-6)
    T_est, *_ = pdsac_bidirectional(a, a_gen, b, b_gen, cfg, torch.Generator().manual_seed(0))
    assert torch.allclose(T_est, T_wrong, atol=1e-6)  # control: unweighted, the majority wins


def test_closed_form_eigenpair_equals_numpy_eigh_on_planar_linear_and_random_neighbourhoods():
    rng = np.random.default_rng(0)
    plane = rng.normal(size=(200, 20, 3)) * [1.0, 0.5, 1e-4]  # nearly flat: the normal is well defined
    line = rng.normal(size=(200, 20, 3)) * [1.0, 1e-3, 1e-3]  # two equal small eigenvalues
    blob = rng.normal(size=(200, 20, 3))
    rotations = Rotation.random(600, random_state=1).as_matrix()
    groups = np.einsum("nij,nkj->nki", rotations, np.concatenate([plane, line, blob]))
    centred = groups - groups.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / 20
    evals, normal = (t.numpy() for t in smallest_eigenpair3(torch.from_numpy(cov).float()))
    ref_vals, ref_vecs = np.linalg.eigh(cov)
    assert np.abs(evals - ref_vals).max() <= 1e-6 * ref_vals.max()
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-6)
    dots = np.abs(np.einsum("ni,ni->n", normal[:400], ref_vecs[:400, :, 0]))  # unsigned normals
    assert dots[:200].min() > 1 - 1e-6  # flat groups
    # equal smallest eigenvalues: any unit vector of their plane is an eigenvector; it must be orthogonal to
    # the line's direction (the largest eigenvector) and have the smallest Rayleigh quotient
    assert np.abs(np.einsum("ni,ni->n", normal[200:400], ref_vecs[200:400, :, 2])).max() < 1e-3
    rayleigh = np.einsum("ni,nij,nj->n", normal.astype(np.float64), cov, normal.astype(np.float64))
    assert np.all(rayleigh <= ref_vals[:, 0] + 1e-6 * ref_vals[:, 2])
