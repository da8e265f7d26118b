"""Model parts: shapes, the efficient edge convolution, the soft pointer, the paper variant, checkpoints."""

import numpy as np
import pytest
import torch

from genreg_core.checkpoint import load_checkpoint, save_checkpoint
from genreg_core.config import ModelConfig
from genreg_core.errors import CheckpointError, ConfigError
from genreg_core.model import PaperGenRegNet, build_model
from genreg_core.model.discriminator import Discriminator
from genreg_core.model.gcnn import EdgeConv, knn_indices
from genreg_core.model.genreg import GenRegNet

SMALL = ModelConfig(num_points=64, k_neighbors=8, gcnn_channels=16, mixer_hidden=(32, 16), feature_dim=16)


def test_efficient_edge_conv_equals_the_naive_gather_form():
    torch.manual_seed(0)
    conv = EdgeConv(3, 16, k=8)
    x = torch.rand(2, 64, 3)
    nb = knn_indices(x, 8)
    assert torch.allclose(conv(x, nb), conv.forward_naive(x, nb), atol=1e-5)


def test_knn_matches_brute_force():
    x = torch.rand(2, 100, 3, dtype=torch.float64)
    idx = knn_indices(x, 5).numpy()
    for c in range(2):
        d = np.linalg.norm(x[c].numpy()[:, None] - x[c].numpy()[None], axis=-1)
        ref = np.argsort(d, axis=1)[:, :5]
        assert all(set(a) == set(b) for a, b in zip(idx[c], ref, strict=True))


def test_paper_variant_generates_per_point_in_the_other_frame():
    """The paper's generator, untrained (identity T-Net, zero last decoder layer): A_g = A - c_A + c_B and
    B_g = B - c_B + c_A; a trained decoder moves each point by its own offset."""
    torch.manual_seed(0)
    net = build_model(ModelConfig(**{**SMALL.__dict__, "architecture": "paper"})).eval()
    assert isinstance(net, PaperGenRegNet)
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    with torch.no_grad():
        out = net(a, b)
    shift = b.mean(1, keepdim=True) - a.mean(1, keepdim=True)
    assert torch.allclose(out.source_generated, a + shift, atol=1e-5)
    assert torch.allclose(out.target_generated, b - shift, atol=1e-5)
    assert out.match_logits is None
    torch.nn.init.normal_(net.decoder.net[-1].weight, std=0.1)
    with torch.no_grad():
        moved = net(a, b).source_generated
    assert float((moved - out.source_generated).abs().max()) > 1e-3
    # every parameter takes part in the loss (DDP needs no find_unused_parameters)
    net.train()
    o = net(a, b)
    (o.source_generated.square().sum() + o.target_generated.square().sum()).backward()
    assert all(p.grad is not None for p in net.parameters())


def test_discriminator_is_permutation_invariant():
    d = Discriminator((16, 32))
    x = torch.rand(3, 50, 3)
    assert torch.allclose(d(x), d(x[:, torch.randperm(50)]), atol=1e-6)


def test_checkpoint_round_trip_and_errors(tmp_path):
    torch.manual_seed(0)
    net = GenRegNet(SMALL)
    for p in net.parameters():  # non-trivial weights, so the round trip is meaningful
        torch.nn.init.normal_(p, std=0.05)
    path = save_checkpoint(net, tmp_path / "m.pt", meta={"steps": 3})
    loaded, meta = load_checkpoint(path)
    assert meta == {"steps": 3} and loaded.config == SMALL
    a, b = torch.rand(1, 64, 3), torch.rand(1, 64, 3)
    with torch.no_grad():
        ref, got = net.eval()(a, b).source_generated, loaded(a, b).source_generated
    assert torch.allclose(ref, got, atol=2e-2)  # fp16 storage
    assert (tmp_path / "m.pt").stat().st_size < 0.6 * sum(p.numel() * 4 for p in net.parameters()) + 20000
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a torch checkpoint"):
        load_checkpoint(tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="N=64"):
        load_checkpoint(path, num_points=512)


def test_ppf_encoder_features_are_unchanged_by_rotation_and_point_order():
    torch.manual_seed(0)
    from scipy.spatial.transform import Rotation

    encoder = GenRegNet(SMALL).encoder.gcnn.eval()
    a = torch.rand(2, 64, 3, dtype=torch.float64)
    a = a - a.mean(1, keepdim=True)
    R = torch.tensor(Rotation.from_euler("xyz", [40, -25, 70], degrees=True).as_matrix())
    perm = torch.randperm(64)
    b = a[:, perm] @ R.T
    encoder.double()
    f_a, f_b = encoder(a), encoder(b)
    assert torch.allclose(f_a[:, perm], f_b, atol=1e-6)
    # ... and it is not trivially constant: features differ between points.
    assert f_a.std(dim=1).mean() > 1e-3


def test_matching_loss_is_lowest_for_the_true_match():
    from genreg_core.training.losses import matching_loss

    torch.manual_seed(0)
    pts = torch.rand(1, 50, 3)
    perm = torch.randperm(50)
    other = pts[:, perm]
    true_logits = torch.full((1, 50, 50), -30.0)
    true_logits[0, torch.arange(50), perm.argsort()] = 0.0  # point i picks its own copy in `other`
    good = matching_loss(torch.log_softmax(true_logits, -1), pts, other, 0.01)
    uniform = matching_loss(torch.log_softmax(torch.zeros(1, 50, 50), -1), pts, other, 0.01)
    assert float(good) < 1e-3 and abs(float(uniform) - np.log(50)) < 1e-3


def test_attention_pointer_picks_real_points_and_passes_gradients_through_the_soft_weights():
    torch.manual_seed(0)
    net = GenRegNet(SMALL)
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    b0 = b - b.mean(1, keepdim=True)
    with torch.no_grad():
        picked = net.eval()(a, b).source_generated - b.mean(1, keepdim=True)  # exactly a point of B
    out = net.train()(a, b)
    trained = out.source_generated - b.mean(1, keepdim=True)
    (trained - 0.3).square().sum().backward()

    def nearest(x: torch.Tensor) -> torch.Tensor:  # exact distances (cdist's matmul form is off by ~1e-4)
        return torch.linalg.norm(x[:, :, None] - b0[:, None], dim=-1).amin(-1)

    assert float(nearest(picked).max()) < 1e-5 and float(nearest(trained.detach()).max()) < 1e-5
    assert float(net.pointer.query.weight.grad.abs().sum()) > 0  # the soft weights still learn


def test_encoder_ablation_without_mixers_is_point_order_equivariant():
    """Without token mixing (the GCNN-only ablation) permuting the input permutes the features."""
    torch.manual_seed(0)
    net = GenRegNet(ModelConfig(**{**SMALL.__dict__, "backbone": "dgcnn"})).eval()
    x = torch.rand(1, 64, 3)
    x = x - x.mean(1, keepdim=True)
    perm = torch.randperm(64)
    with torch.no_grad():
        f, f_perm = net.encoder(x), net.encoder(x[:, perm])
    assert f.shape == (1, 64, SMALL.feature_dim)
    assert torch.allclose(f[:, perm], f_perm, atol=1e-5)


def test_knn_indices_equal_a_kd_tree_at_the_shipped_size_ties_included():
    from scipy.spatial import cKDTree

    torch.manual_seed(3)
    x = torch.rand(2, 512, 3)
    x[1, 400:] = x[1, :112]  # repeated points (subsampling a small cloud repeats rows): ties
    idx = knn_indices(x, 20).numpy()
    for c in range(2):
        points = x[c].double().numpy()
        ref_dist, ref_idx = cKDTree(points).query(points, k=20)
        got_dist = np.linalg.norm(points[idx[c]] - points[:, None], axis=-1)
        np.testing.assert_allclose(got_dist, ref_dist, atol=1e-12)  # the k nearest, nearest first
        if c == 0:  # distinct distances: the very same neighbours in the same order
            np.testing.assert_array_equal(idx[c], ref_idx)
    assert (idx[1][:, 0] <= np.arange(512)).all()  # a repeated point's first neighbour: its lowest-index copy


def test_point_mlp_equals_its_conv1d_layers():
    """`PointMLP` computes what its Conv1d / GroupNorm / ReLU layers compute in sequence, gradients too."""
    from torch import nn

    from genreg_core.model.layers import point_mlp

    torch.manual_seed(0)
    mlp = point_mlp((4, 32, 64), norm="group").double()
    for m in mlp.modules():  # non-trivial affine parameters
        if isinstance(m, nn.GroupNorm):
            nn.init.normal_(m.weight)
            nn.init.normal_(m.bias)
    x = torch.randn(3, 4, 500, dtype=torch.float64)
    reference = nn.Sequential(*mlp)(x)  # the plain modules, Conv1d path
    assert torch.allclose(mlp(x), reference, atol=1e-10)
    x.requires_grad_(True)
    (grad,) = torch.autograd.grad(mlp(x).square().sum(), x)
    assert torch.allclose(grad, torch.autograd.grad(nn.Sequential(*mlp)(x).square().sum(), x)[0], atol=1e-9)


def test_the_three_stages_compose_to_forward_and_every_parameter_learns():
    torch.manual_seed(0)
    net = GenRegNet(SMALL)
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    with torch.no_grad():
        net.eval()
        enc = net.encode(a, b)
        staged = net.generate(enc, net.interact(enc))
        whole = net(a, b)
    assert torch.equal(staged.source_generated, whole.source_generated)
    log_w_a = whole.match_logits[0]
    assert log_w_a.shape == (2, 64, 64) and torch.allclose(log_w_a.exp().sum(-1), torch.ones(2, 64))
    with pytest.raises(ValueError, match="64 points"):
        net(torch.rand(1, 32, 3), torch.rand(1, 32, 3))
    net.train()
    out = net(a, b)
    (out.source_generated.square().sum() + out.target_generated.square().sum()).backward()
    assert all(p.grad is not None for p in net.parameters())  # DDP needs no find_unused_parameters
    for part in (net.encoder.gcnn, net.encoder.mixer1, net.encoder.mixer2, net.pointer):
        assert sum(float(p.grad.abs().sum()) for p in part.parameters()) > 0


def test_model_config_rejects_unknown_choices_and_ranges():
    with pytest.raises(ConfigError, match="backbone"):
        ModelConfig(backbone="pointnet2")
    with pytest.raises(ConfigError, match="architecture"):
        ModelConfig(architecture="transformer")
    with pytest.raises(ConfigError, match="num_points"):
        ModelConfig(num_points=8)


NEW = ModelConfig(**{**SMALL.__dict__, "point_feature": "knn", "generation": "neighbours", "generation_k": 6,
                     "overlap_head": True})


def test_neighbour_generation_is_rotation_equivariant_and_leaves_the_samples():
    """Rotating and moving B moves A_g the same way (to float precision); A_g is a convex combination of
    the pick's 6 nearest neighbours in B, so it lies in their hull, not necessarily on a sample."""
    from scipy.spatial.transform import Rotation

    torch.manual_seed(0)
    net = GenRegNet(NEW).double().eval()
    a, b = torch.rand(1, 64, 3, dtype=torch.float64), torch.rand(1, 64, 3, dtype=torch.float64)
    R = torch.tensor(Rotation.from_euler("xyz", [120, -40, 75], degrees=True).as_matrix())
    t = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
    with torch.no_grad():
        out = net(a, b)
        moved = net(a, b @ R.T + t)
    assert torch.allclose(moved.source_generated, out.source_generated @ R.T + t, atol=1e-9)
    assert torch.allclose(moved.target_generated, out.target_generated, atol=1e-9)  # B_g is in A's frame
    nearest = torch.cdist(out.source_generated[0], b[0]).amin(-1)
    assert float(nearest.max()) > 1e-4  # off B's samples somewhere
    o_a, o_b = out.overlap()
    assert o_a.shape == (1, 64) and o_b.shape == (1, 64) and ((o_a > 0) & (o_a < 1)).all()
    with torch.no_grad():
        o_moved = moved.overlap()[0]
    assert torch.allclose(o_a, o_moved, atol=1e-9)  # invariant


def test_knn_point_feature_ignores_a_crop_elsewhere():
    """The 'knn' point input is local: points whose neighbourhoods a crop leaves intact keep it, while
    the distance to the centroid moves."""
    from genreg_core.model.invariant import invariant_geometry, point_inputs

    torch.manual_seed(0)
    pts = torch.rand(1, 400, 3, dtype=torch.float64)
    keep = pts[0, :, 0] < 0.6
    inner = pts[0, keep, 0] < 0.4  # far from the cut: the same 8 neighbours

    def inputs(cloud: torch.Tensor, kind: str) -> torch.Tensor:
        cloud = cloud - cloud.mean(1, keepdim=True)
        edge, point, _ = invariant_geometry(cloud, knn_indices(cloud, 8))
        return point_inputs(point, edge, kind, 10.0)[0]

    full, part = pts, pts[:, keep]
    assert torch.allclose(inputs(full, "knn")[keep][inner], inputs(part, "knn")[inner], atol=1e-9)
    assert not torch.allclose(inputs(full, "centroid")[keep][inner], inputs(part, "centroid")[inner], atol=1e-3)


LOCAL_GN = ModelConfig(num_points=64, k_neighbors=8, gcnn_channels=16, feature_dim=16, backbone="dgcnn",
                       point_feature="knn", generation="neighbours", generation_k=6, overlap_head=True)
LOCAL_NONE = ModelConfig(num_points=64, k_neighbors=8, gcnn_channels=16, feature_dim=16, backbone="dgcnn",
                         point_feature="knn", generation="neighbours", generation_k=6, overlap_head=True,
                         norm="none", pointer_centring=False)


def _group_moments(model: torch.nn.Module, cloud: torch.Tensor) -> dict:
    """Each GroupNorm's per-group input mean and variance, and the pointer's query / key means, on one
    centred cloud (1, N, 3) (the statistics the model uses on it)."""
    from genreg_core.model.fold import NormStatistics

    seen: dict = {}
    names = {m: n for n, m in model.named_modules()}
    hooks = [m.register_forward_hook(lambda mod, inp, _o: seen.__setitem__(names[mod], (
        inp[0].reshape(1, mod.num_groups, -1).mean(-1)[0], inp[0].reshape(1, mod.num_groups, -1).var(-1, unbiased=False)[0])))
        for m in model.modules() if isinstance(m, torch.nn.GroupNorm)]
    with torch.no_grad():
        f = model.encoder(cloud)
    for h in hooks:
        h.remove()
    return NormStatistics(seen, model.pointer.query(f).mean(1)[0], model.pointer.key(f).mean(1)[0])


def test_folding_fixed_statistics_gives_the_groupnorm_model_on_a_cloud_with_those_statistics():
    from genreg_core.model.fold import fold_statistics

    torch.manual_seed(0)
    model = GenRegNet(LOCAL_GN).eval()
    with torch.no_grad():  # non-trivial affine parameters, positive scales
        for m in model.modules():
            if isinstance(m, torch.nn.GroupNorm):
                m.weight.uniform_(0.5, 2.0), m.bias.uniform_(-0.5, 0.5)
    a = torch.rand(1, 64, 3)
    folded = fold_statistics(model, _group_moments(model, a - a.mean(1, keepdim=True)))
    assert folded.config.norm == "none" and not folded.config.pointer_centring
    assert not any(isinstance(m, torch.nn.GroupNorm) for m in folded.modules())
    with torch.no_grad():  # a pair of the same cloud: both clouds have the folded statistics
        ref, out = model.encode(a, a), folded.encode(a, a)
        assert torch.allclose(ref.f_a, out.f_a, atol=1e-5)
        m_ref, m_out = model.interact(ref), folded.interact(out)
    assert torch.allclose(m_ref.log_w_a, m_out.log_w_a, atol=1e-4)
    assert torch.allclose(m_ref.overlap_a, m_out.overlap_a, atol=1e-4)
    with torch.no_grad():
        model.encoder.gcnn.context.norm.weight[0] = -1.0
    with pytest.raises(CheckpointError, match="non-positive scale"):
        fold_statistics(model, _group_moments(model, a - a.mean(1, keepdim=True)))


def test_statistics_free_features_ignore_a_crop_elsewhere_and_groupnorm_features_do_not():
    """norm none + knn point feature + dgcnn backbone: a point whose neighbourhood a crop leaves
    intact keeps its features; with GroupNorm they move."""
    torch.manual_seed(0)
    pts = torch.rand(1, 400, 3)
    keep = pts[0, :, 0] < 0.8
    inner = pts[0, keep, 0] < 0.2  # far from the cut: the same three-hop neighbourhoods (normals, PPF, edge conv)
    assert inner.sum() > 50
    for norm, centring, local in (("none", False, True), ("group", True, False)):
        model = GenRegNet(ModelConfig(**{**LOCAL_GN.__dict__, "norm": norm, "pointer_centring": centring})).eval()
        with torch.no_grad():
            full, part = model.encoder(pts - pts.mean(1, keepdim=True)), model.encoder(pts[:, keep] - pts[:, keep].mean(1, keepdim=True))
            same = torch.allclose(full[0, keep][inner], part[0, inner], atol=1e-5)
        assert same == local, norm


def test_widening_keeps_the_function_and_the_new_channels_can_learn():
    from genreg_core.model.fold import widen

    torch.manual_seed(0)
    model = GenRegNet(LOCAL_NONE).eval()
    wide = widen(model, 2 * LOCAL_NONE.gcnn_channels, 2 * LOCAL_NONE.feature_dim)
    assert wide.encoder.mixer1.weight.shape == (2 * LOCAL_NONE.feature_dim, 2 * LOCAL_NONE.gcnn_channels)
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    with torch.no_grad():
        ref, out = model(a, b), wide(a, b)
    assert torch.allclose(ref.match_logits[0], out.match_logits[0], atol=1e-5)
    assert torch.allclose(ref.overlap_logits[0], out.overlap_logits[0], atol=1e-5)
    wide.train()
    wide(a, b).match_logits[0].max(dim=-1).values.sum().backward()
    assert wide.pointer.query.weight.grad[:, LOCAL_NONE.feature_dim:].abs().sum() > 0
    with pytest.raises(CheckpointError, match="cannot narrow"):
        widen(model, LOCAL_NONE.gcnn_channels // 2, LOCAL_NONE.feature_dim)
