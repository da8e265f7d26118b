"""Model parts: shapes, the efficient edge convolution, per-point generation, checkpoints."""

import numpy as np
import pytest
import torch

from genreg_core.checkpoint import load_checkpoint, save_checkpoint
from genreg_core.config import ModelConfig
from genreg_core.errors import CheckpointError, ConfigError
from genreg_core.geometry import apply_transform, random_transform
from genreg_core.model.discriminator import Discriminator
from genreg_core.model.gcnn import EdgeConv, knn_indices
from genreg_core.model.genreg import GenRegNet
from genreg_core.model.prealign import pca_prealign

SMALL = ModelConfig(num_points=64, k_neighbors=8, tnet_channels=(16, 32, 64), tnet_head=(32, 16),
                    gcnn_channels=16, mixer_hidden=(32, 16), feature_dim=16, decoder_channels=(32, 16, 8))


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


def test_generation_is_per_point_and_shapes_are_right():
    torch.manual_seed(0)
    net = GenRegNet(SMALL).eval()
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    out = net(a, b)
    assert out.source_generated.shape == (2, 64, 3) and out.target_generated.shape == (2, 64, 3)
    assert out.tnet.shape == (2, 4, 4)
    assert torch.allclose(out.target_generated, b - b.mean(1, keepdim=True) + a.mean(1, keepdim=True), atol=1e-5)
    # Untrained (zero-initialised last layers): A_g is A moved by B's centroid minus A's centroid.
    shift = b.mean(1, keepdim=True) - a.mean(1, keepdim=True)
    assert torch.allclose(out.source_generated, a + shift, atol=1e-5)
    with pytest.raises(ValueError):
        net(torch.rand(1, 32, 3), torch.rand(1, 32, 3))


def test_pca_prealign_recovers_a_rotation_of_an_anisotropic_cloud():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 3)) * np.array([3.0, 1.5, 0.5])
    a[:, 0] += 0.8 * a[:, 0] ** 2 / 9.0  # break the sign symmetry of the long axis
    a -= a.mean(0)
    T = random_transform(rng, 45, 0)
    b = apply_transform(T, a)
    R = pca_prealign(torch.tensor(a)[None], torch.tensor(b)[None])[0].numpy()
    assert np.allclose(R, T[:3, :3], atol=0.05)


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
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="N=64"):
        load_checkpoint(path, num_points=512)


def test_local_interaction_sees_the_nearest_neighbour_offset():
    from genreg_core.model.genreg import nearest_neighbour_context

    pts = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    other = torch.tensor([[[1.1, 0.0, 0.0], [0.0, 0.2, 0.0], [5.0, 5.0, 5.0]]])
    feats = torch.tensor([[[1.0], [2.0], [3.0]]])
    ctx = nearest_neighbour_context(pts, other, feats)
    assert torch.allclose(ctx[0, 0], torch.tensor([0.0, 0.2, 0.0, 2.0]))
    assert torch.allclose(ctx[0, 1], torch.tensor([0.1, 0.0, 0.0, 1.0]))
    net = GenRegNet(ModelConfig(**{**SMALL.__dict__, "interaction": "local"})).eval()
    out = net(torch.rand(2, 64, 3), torch.rand(2, 64, 3))
    assert out.source_generated.shape == (2, 64, 3)


def test_attention_interaction_generates_convex_combinations_of_the_other_cloud():
    """Untrained (zero decoder, identity T-Net): A_g - c_B is a weighted mean of B's centred points."""
    torch.manual_seed(0)
    net = GenRegNet(ModelConfig(**{**SMALL.__dict__, "interaction": "attention"})).eval()
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3) * 2.0
    with torch.no_grad():
        out = net(a, b)
    centred = out.source_generated - b.mean(1, keepdim=True)
    b0 = b - b.mean(1, keepdim=True)
    assert (centred >= b0.amin(1, keepdim=True) - 1e-5).all() and (centred <= b0.amax(1, keepdim=True) + 1e-5).all()
    assert out.source_generated.shape == (2, 64, 3)


def test_both_generated_clouds_are_in_the_other_frame_with_pca_prealignment():
    """Untrained (identity T-Net, zero decoder): A_g = R_pre (A - c_A) + c_B and B_g = R_pre^T (B - c_B) + c_A,
    so PDSAC on both directions recovers the same transform (B_g is mapped back with the inverse)."""
    rng = np.random.default_rng(0)
    shape = rng.normal(size=(64, 3)) * np.array([3.0, 1.5, 0.5])
    shape[:, 0] += 0.3 * shape[:, 0] ** 2
    T = random_transform(rng, 40, 0.5)
    a = torch.tensor(shape, dtype=torch.float32)[None]
    b = torch.tensor(apply_transform(T, shape), dtype=torch.float32)[None]
    net = GenRegNet(ModelConfig(**{**SMALL.__dict__, "prealign": "pca"})).eval()
    with torch.no_grad():
        out = net(a, b)
    R = out.prealign[0]
    c_a, c_b = a.mean(1), b.mean(1)
    assert torch.allclose(out.source_generated[0], (a[0] - c_a) @ R.T + c_b, atol=1e-5)
    assert torch.allclose(out.target_generated[0], (b[0] - c_b) @ R + c_a, atol=1e-5)
    assert torch.allclose(R, torch.tensor(T[:3, :3], dtype=torch.float32), atol=1e-3)


@pytest.mark.parametrize("backbone", ["pointmixer", "pointnet2"])
def test_ppf_encoder_features_are_unchanged_by_rotation_and_point_order(backbone):
    torch.manual_seed(0)
    from scipy.spatial.transform import Rotation

    cfg = SMALL.__class__(**{**SMALL.__dict__, "encoder": "ppf", "tnet": False, "backbone": backbone})
    net = GenRegNet(cfg)
    encoder = (net.encoder.gcnn if backbone == "pointmixer" else net.encoder).eval()
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
    cfg = ModelConfig(**{**SMALL.__dict__, "encoder": "ppf", "tnet": False, "interaction": "attention",
                         "attention_sigma": 0.0, "offset_limit": 0.02})
    net = GenRegNet(cfg)
    a, b = torch.rand(2, 64, 3), torch.rand(2, 64, 3)
    b0 = b - b.mean(1, keepdim=True)
    with torch.no_grad():
        picked = net.eval()(a, b).source_generated - b.mean(1, keepdim=True)  # zero decoder: exactly a point of B
    out = net.train()(a, b)
    trained = out.source_generated - b.mean(1, keepdim=True)
    (trained - 0.3).square().sum().backward()

    def nearest(x: torch.Tensor) -> torch.Tensor:  # exact distances (cdist's matmul form is off by ~1e-4)
        return torch.linalg.norm(x[:, :, None] - b0[:, None], dim=-1).amin(-1)

    assert float(nearest(picked).max()) < 1e-5 and float(nearest(trained.detach()).max()) < 1e-5
    assert float(net.pointer.query.weight.grad.abs().sum()) > 0  # the soft weights still learn


def test_without_decoder_offsets_the_generated_points_are_the_pointers_picks():
    torch.manual_seed(0)
    base = {**SMALL.__dict__, "encoder": "ppf", "tnet": False, "interaction": "attention", "attention_sigma": 0.0}
    net = GenRegNet(ModelConfig(**{**base, "decoder_offsets": False})).eval()
    torch.nn.init.normal_(net.decoder.net[-1].weight)  # a decoder that would move the points
    a, b = torch.rand(1, 64, 3), torch.rand(1, 64, 3)
    with torch.no_grad():
        out = net(a, b)
    b0 = b - b.mean(1, keepdim=True)
    log_w_a, _ = out.match_logits
    picks = b0[0, log_w_a[0].argmax(-1)] + b.mean(1)[0]
    assert torch.allclose(out.source_generated[0], picks, atol=1e-6)
    with pytest.raises(ConfigError):
        ModelConfig(**{**base, "interaction": "global", "decoder_offsets": False})


def test_encoder_ablation_without_mixers_is_point_order_equivariant():
    """Without token mixing (the GCNN-only ablation) permuting the input permutes the features."""
    torch.manual_seed(0)
    net = GenRegNet(ModelConfig(**{**SMALL.__dict__, "encoder": "ppf", "backbone": "dgcnn"})).eval()
    x = torch.rand(1, 64, 3)
    x = x - x.mean(1, keepdim=True)
    perm = torch.randperm(64)
    with torch.no_grad():
        f, f_perm = net.encoder(x), net.encoder(x[:, perm])
    assert f.shape == (1, 64, SMALL.feature_dim)
    assert torch.allclose(f[:, perm], f_perm, atol=1e-5)


def test_farthest_point_sampling_picks_the_farthest_point_each_time():
    """Each pick is the point farthest (scipy cdist) from those already picked; the first is the farthest
    from the origin; no point is picked twice."""
    from scipy.spatial.distance import cdist

    from genreg_core.model.pointnet2 import farthest_point_sample

    x = torch.rand(2, 200, 3, dtype=torch.float64) - 0.5
    idx = farthest_point_sample(x, 30).numpy()
    for cloud, picks in zip(x.numpy(), idx, strict=True):
        assert len(set(picks)) == 30 and picks[0] == np.argmax(np.linalg.norm(cloud, axis=1))
        for m in range(1, 30):
            nearest_pick = cdist(cloud, cloud[picks[:m]]).min(axis=1)
            assert picks[m] == np.argmax(nearest_pick)


def test_knn_query_matches_brute_force():
    from scipy.spatial.distance import cdist

    from genreg_core.model.gcnn import knn_query

    q, p = torch.rand(2, 30, 3, dtype=torch.float64), torch.rand(2, 80, 3, dtype=torch.float64)
    dist, idx = knn_query(q, p, 3)
    for b in range(2):
        d = cdist(q[b].numpy(), p[b].numpy())
        np.testing.assert_array_equal(idx[b].numpy(), np.argsort(d, axis=1)[:, :3])
        np.testing.assert_allclose(dist[b].numpy(), np.sort(d, axis=1)[:, :3], atol=1e-12)


def test_pointnet2_backbone_needs_the_invariant_inputs():
    with pytest.raises(ConfigError, match="pointnet2"):
        ModelConfig(**{**SMALL.__dict__, "backbone": "pointnet2"})
    with pytest.raises(ConfigError, match="backbone"):
        ModelConfig(**{**SMALL.__dict__, "backbone": "transformer"})


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
