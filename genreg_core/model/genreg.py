"""GenRegNet: the generator every shipped model uses (paper Fig. 2, with our measured levers).

Frames: A (source) and B (target) are (B, N, 3) clouds in their own frames (`genreg_core.geometry`).
The network generates A_g, point i of A expressed in B's frame, and B_g, point i of B expressed in A's
frame; PDSAC turns the pairs (A_i, A_g,i) and (B_g,i, B_i) into one transform. Three stages:

1. encode (paper Sec. 3.1): each cloud is centred on its centroid; a rotation-invariant point-pair-feature
   stem and an edge convolution (`invariant.InvariantEncoder`, in the GCNN's place) and the paper's two
   mixer layers (backbone "pointmixer"; "dgcnn": a linear layer instead) give per-point features F.
2. interact (the feature interaction, our soft pointer): each point of A attends to B's points by the
   cosine of learned, per-cloud-centred query/key features times a learned sharpness (and B to A).
   With `overlap_head`, an MLP on each point's features, its best match score and its cycle distance
   (how far the pick of its pick lands from it) scores whether the point has a counterpart at all.
3. generate: generation "pick": A_g,i is the best-matching point of B (hard pick; training passes
   gradients through the soft mean, straight-through); "neighbours": the match-weighted mean of the
   pick's nearest neighbours in B, so A_g can fall between B's samples. Moved back by B's centroid;
   likewise B_g.

Because every input to the match is invariant, the generated correspondences do not depend on the
rotation between the clouds, and A_g (a convex combination of B's points) moves with B: equivariant by
construction. The paper's decoder lives in `genreg_core.model.paper`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from genreg_core import kernels
from genreg_core.config import ModelConfig
from genreg_core.model.gcnn import knn_indices
from genreg_core.model.invariant import InvariantEncoder
from genreg_core.model.layers import centroid, gather_neighbours, mlp, zero_last_layer
from genreg_core.model.mixer import MixerLayer


@dataclass
class GenRegOutput:
    """Generated clouds of one forward pass (both generator variants)."""

    source_generated: torch.Tensor  # A_g (B, N, 3), in B's frame
    target_generated: torch.Tensor  # B_g (B, N, 3), in A's frame
    # soft pointer only: log match weights, A's points onto B's (B, N, M) and B's onto A's (B, M, N)
    match_logits: tuple[torch.Tensor, torch.Tensor] | None = None
    # overlap head only: per-point overlap logits of A (B, N) and B (B, M)
    overlap_logits: tuple[torch.Tensor, torch.Tensor] | None = None

    def overlap(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Overlap probabilities of A's and B's points, or None without an overlap head."""
        return None if self.overlap_logits is None else tuple(torch.sigmoid(x) for x in self.overlap_logits)


@dataclass
class Encoded:
    """Stage 1 output: centred clouds, their centroids, per-point features and kNN graphs."""

    a0: torch.Tensor  # (B, N, 3) A - c_A
    b0: torch.Tensor  # (B, M, 3) B - c_B
    c_a: torch.Tensor  # (B, 1, 3)
    c_b: torch.Tensor
    # (B, N, C) per-point features F; at inference with backbone "dgcnn" the GCNN features h that F is one
    # linear layer of (`GenRegNet.first_products` folds that layer into the interaction's first products)
    f_a: torch.Tensor
    f_b: torch.Tensor  # (B, M, C)
    knn_a: torch.Tensor | None = None  # (B, N, k) each point's k_neighbors nearest in A, nearest first
    knn_b: torch.Tensor | None = None  # (B, M, k) likewise in B


class PointMixerEncoder(nn.Module):
    """Invariant GCNN then two mixer layers (or one linear layer, backbone "dgcnn"):
    (B, N, 3) centred cloud -> (B, N, feature_dim)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.gcnn = InvariantEncoder(cfg.gcnn_channels, cfg.k_neighbors, norm=cfg.norm, point_feature=cfg.point_feature)
        if cfg.backbone == "dgcnn":
            self.mixer1: nn.Module = nn.Linear(cfg.gcnn_channels, cfg.feature_dim)
            self.mixer2: nn.Module = nn.Identity()
        else:
            h1, h2 = cfg.mixer_hidden
            self.mixer1 = MixerLayer(cfg.num_points, cfg.gcnn_channels, h1, cfg.feature_dim)
            self.mixer2 = MixerLayer(cfg.num_points, cfg.feature_dim, h2, cfg.feature_dim)
            for mixer in (self.mixer1, self.mixer2):  # token mixing starts as a no-op: point order is random
                zero_last_layer(mixer.token_mlp)

    def forward(self, points: torch.Tensor, neighbours: torch.Tensor | None = None) -> torch.Tensor:
        """neighbours: the kNN graph of `points` (B, N, k), or None to build it."""
        return self.mixer2(self.mixer1(self.gcnn(points, neighbours)))


class SoftPointer(nn.Module):
    """Match logits of each point of x onto the points of y: cosine similarity of learned query/key
    features, each centred over its cloud (`centred`; else the biases carry the centre), times a learned
    sharpness (starts at `sharpness`)."""

    def __init__(self, channels: int, dim: int, sharpness: float = 10.0, centred: bool = True) -> None:
        super().__init__()
        self.centred = centred
        self.query = nn.Linear(channels, dim)
        self.key = nn.Linear(channels, dim)
        self.log_sharpness = nn.Parameter(torch.tensor(float(sharpness)).log())

    def forward(self, f_x: torch.Tensor, f_y: torch.Tensor) -> torch.Tensor:
        """(B, N, C), (B, M, C) features -> log weights (B, N, M), normalised over M."""
        return self.log_weights(self.embed(self.query, f_x), self.embed(self.key, f_y))

    def embed(self, projection: nn.Linear, f: torch.Tensor) -> torch.Tensor:
        """Unit query or key vectors of each cloud (B, N, dim), centred over the cloud first (`centred`)."""
        return self.unit(projection(f))

    def unit(self, x: torch.Tensor) -> torch.Tensor:
        """Projected queries or keys (B, N, dim) -> unit vectors, centred over the cloud first (`centred`)."""
        if self.centred:  # the component all points share carries no match
            x = x - x.mean(dim=1, keepdim=True)
        return nn.functional.normalize(x, dim=-1)

    def log_weights(self, q: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """Sharpened cosines of unit queries (B, N, dim) and keys (B, M, dim), log-softmax over M."""
        logits, sharpness = q @ k.transpose(1, 2), self.log_sharpness.exp()
        logits = logits * sharpness if torch.is_grad_enabled() else logits.mul_(sharpness)
        return torch.log_softmax(logits, dim=-1)


@dataclass
class Match:
    """Stage 2 output: log match weights A -> B (B, N, M) and B -> A (B, M, N), each point's best match
    (the argmax of its row, found once for the overlap head and generation), overlap logits or None."""

    log_w_a: torch.Tensor
    log_w_b: torch.Tensor
    best_a: torch.Tensor  # (B, N) index into B
    best_b: torch.Tensor  # (B, M) index into A
    overlap_a: torch.Tensor | None = None  # (B, N)
    overlap_b: torch.Tensor | None = None  # (B, M)


def pick(log_w: torch.Tensor, best: torch.Tensor, y: torch.Tensor, straight_through: bool) -> torch.Tensor:
    """The best-matching point of y (B, M, 3) for each row of log_w (B, N, M), `best` (B, N) its argmax:
    a real point, since a soft mean of several candidates lands between them, off the surface. With
    `straight_through` (training) gradients flow through the soft mean."""
    best = torch.gather(y, 1, best[..., None].expand(-1, -1, 3))
    if not straight_through:
        return best
    soft = log_w.exp() @ y
    return best + (soft - soft.detach())


def neighbour_mix(log_w: torch.Tensor, best: torch.Tensor, y: torch.Tensor, k: int,
                  knn: torch.Tensor | None = None) -> torch.Tensor:
    """For each row of log_w (B, N, M), `best` (B, N) its argmax: the mean of the best match's k nearest
    neighbours in y (B, M, 3), the best included, weighted by their renormalised match weights. A convex
    combination of y's points chosen by invariant quantities, so it moves with y under any rigid motion.
    knn: y's kNN graph (B, M, >= k), nearest first, to take the k nearest from, or None to query them. With
    a graph, where `kernels.usable`: compiled (`kernels.neighbour_mix`), equal to float32 rounding."""
    if knn is not None and kernels.usable(log_w, y):  # the same formula in one compiled pass
        arrays = (x.contiguous().numpy() for x in (log_w, best, y, knn))
        return torch.from_numpy(kernels.neighbour_mix(*arrays, k))
    knn = knn_indices(y, k) if knn is None else knn[..., :k]  # (B, M, k), nearest first (the point itself)
    candidates = torch.gather(knn, 1, best[..., None].expand(-1, -1, k))  # (B, N, k)
    weights = torch.softmax(torch.gather(log_w, 2, candidates), dim=-1)
    points = gather_neighbours(y, candidates)  # (B, N, k, 3)
    return (weights[..., None] * points).sum(dim=2)


def row_max(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`x.max(dim=-1)` (value, first index of it); where `kernels.usable`, the value by the vectorised `amax`
    and its first index compiled (`kernels.first_index`): torch's indexed max is not vectorised (0.25 ms for
    512 x 512, against 0.04). A row holding NaN (overflowing input) has no element equal to its max: torch's
    own max gives it the NaN's index."""
    if not kernels.usable(x):
        return tuple(x.max(dim=-1))
    top = x.amax(dim=-1)
    if torch.isnan(top).any():
        return tuple(x.max(dim=-1))
    return top, torch.from_numpy(kernels.first_index(x.contiguous().numpy(), top.numpy()))


def cycle_distance(best_x: torch.Tensor, best_y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """|x_i - x_i'| where i' is the pick of the pick of x_i (x -> y -> x): zero for consistent matches.
    Picks x -> y (B, N), y -> x (B, M), points (B, N, 3) -> (B, N)."""
    back = torch.gather(best_y, 1, best_x)  # (B, N)
    return torch.linalg.norm(x - torch.gather(x, 1, back[..., None].expand(-1, -1, 3)), dim=-1)


class OverlapHead(nn.Module):
    """Overlap logit of each point from its features, its best match score (max log weight, shifted by
    log M) and its cycle distance (times `scale`, unit-box inputs)."""

    def __init__(self, channels: int, hidden: int = 64, scale: float = 10.0) -> None:
        super().__init__()
        self.scale = scale
        self.mlp = mlp((channels + 2, hidden, 1))

    def forward(self, f: torch.Tensor, best_log_w: torch.Tensor, candidates: int, cycle: torch.Tensor) -> torch.Tensor:
        """f (B, N, C), each point's largest log match weight (B, N) over `candidates` points, cycle (B, N)."""
        best = best_log_w[..., None] + torch.log(torch.tensor(float(candidates)))
        return self.mlp(torch.cat([f, best, self.scale * cycle[..., None]], dim=-1))[..., 0]

    def from_features_product(self, first: torch.Tensor, best_log_w: torch.Tensor, candidates: int,
                              cycle: torch.Tensor) -> torch.Tensor:
        """`forward` with the first layer's product of the features and its bias already taken, `first`
        (B, N, hidden): the two scalar inputs' columns are added to it, then the rest of the MLP."""
        c = self.mlp[0].weight.shape[1] - 2  # the features' width; the score's and the cycle's columns follow
        w_best, w_cycle = self.mlp[0].weight[:, c], self.mlp[0].weight[:, c + 1]
        best = best_log_w[..., None] + math.log(candidates)
        first = first + best * w_best + (self.scale * cycle[..., None]) * w_cycle
        return self.mlp[1:](first)[..., 0]


class GenRegNet(nn.Module):
    """The generator. `forward(a, b)` -> GenRegOutput. Inputs must hold exactly cfg.num_points points."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = cfg or ModelConfig()
        self.encoder = PointMixerEncoder(self.config)
        self.pointer = SoftPointer(self.config.feature_dim, self.config.attention_dim,
                                   centred=self.config.pointer_centring)
        self.overlap = OverlapHead(self.config.feature_dim) if self.config.overlap_head else None
        self._first_products: tuple[tuple, tuple[torch.Tensor, torch.Tensor]] | None = None  # (weights' key, W, b)

    def knn_graph(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """The kNN graph `encode` uses: (2B, N, k) over the centred clouds, A's batch first (scipy, outside
        torch's graph: compiled or exported networks take it as an input)."""
        return knn_indices(torch.cat([a - centroid(a), b - centroid(b)], dim=0), self.config.k_neighbors)

    def encode(self, a: torch.Tensor, b: torch.Tensor, graph: torch.Tensor | None = None) -> Encoded:
        """Stage 1: centre both clouds, per-point invariant features (one batched pass for both).
        graph: `knn_graph(a, b)` if already built, else None to build it."""
        n = self.config.num_points
        if a.shape[1] != n or b.shape[1] != n:
            raise ValueError(f"GenRegNet expects {n} points, got {a.shape[1]} and {b.shape[1]}")
        c_a, c_b = centroid(a), centroid(b)
        a0, b0 = a - c_a, b - c_b
        centred = torch.cat([a0, b0], dim=0)
        graph = knn_indices(centred, self.config.k_neighbors) if graph is None else graph
        encoder = self.encoder.gcnn if self.folds_backbone() else self.encoder
        f_a, f_b = encoder(centred, graph).chunk(2, dim=0)
        return Encoded(a0, b0, c_a, c_b, f_a, f_b, *graph.chunk(2, dim=0))

    def folds_backbone(self) -> bool:
        """Whether this pass folds the backbone "dgcnn"'s linear layer F = M h + m into the interaction (no
        gradient recorded): `encode` then stops at the GCNN features h, and `interact` takes its first
        products from them (`first_products`)."""
        return self.config.backbone == "dgcnn" and not torch.is_grad_enabled()

    def first_products(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Inference: the interaction's first linear maps of the features F, stacked into one (W, b): the
        pointer's query and key projections and, with the overlap head, its first layer's feature columns.
        F is only ever read by these maps, so when F = M h + m (`folds_backbone`) they are composed with it,
        W (M h + m) + b = (W M) h + (W m + b), and one product of the narrower h gives all three: the
        same values up to float32 rounding, at a third of the products at backbone "dgcnn"'s widths. Kept
        until a weight changes (its tensor's version: an optimiser step, `load_state_dict`, an in-place edit)."""
        maps = [self.pointer.query, self.pointer.key] + ([] if self.overlap is None else [self.overlap.mlp[0]])
        folds = self.folds_backbone()
        params = [p for m in maps + ([self.encoder.mixer1] if folds else []) for p in (m.weight, m.bias)]
        key = tuple((p.data_ptr(), p._version) for p in params)  # any change of a weight changes its version
        if self._first_products is not None and self._first_products[0] == key:
            return self._first_products[1]
        c = self.config.feature_dim
        weight = torch.cat([m.weight[:, :c] for m in maps])
        bias = torch.cat([m.bias for m in maps])
        if folds:
            mixer = self.encoder.mixer1
            weight, bias = weight @ mixer.weight, torch.addmv(bias, weight, mixer.bias)
        self._first_products = key, (weight, bias)
        return weight, bias

    def interact(self, enc: Encoded) -> Match:
        """Stage 2: log match weights both ways and, with the overlap head, per-point overlap logits. Without
        gradient the same values from the first products of both clouds' rows at once (`first_products`;
        `encode` gives both clouds N points), then the pointer's log weights and the overlap head's
        remaining layers."""
        inference = not torch.is_grad_enabled()
        if inference:
            weight, bias = self.first_products()
            d = self.config.attention_dim
            first = nn.functional.linear(torch.cat([enc.f_a, enc.f_b]), weight, bias).chunk(2)  # both clouds' rows
            (q_a, k_a), (q_b, k_b) = ((self.pointer.unit(x[..., :d]), self.pointer.unit(x[..., d: 2 * d]))
                                      for x in first)
            log_w_a, log_w_b = self.pointer.log_weights(q_a, k_b), self.pointer.log_weights(q_b, k_a)
        else:
            log_w_a, log_w_b = self.pointer(enc.f_a, enc.f_b), self.pointer(enc.f_b, enc.f_a)
        (top_a, best_a), (top_b, best_b) = row_max(log_w_a), row_max(log_w_b)  # one pass: value and index
        if self.overlap is None:
            return Match(log_w_a, log_w_b, best_a, best_b)
        cycle_a, cycle_b = cycle_distance(best_a, best_b, enc.a0), cycle_distance(best_b, best_a, enc.b0)
        if inference:
            overlap_a, overlap_b = (self.overlap.from_features_product(x[..., 2 * d:], top, w.shape[-1], cycle)
                                    for x, top, w, cycle in ((first[0], top_a, log_w_a, cycle_a),
                                                             (first[1], top_b, log_w_b, cycle_b)))
        else:
            overlap_a = self.overlap(enc.f_a, top_a, log_w_a.shape[-1], cycle_a)
            overlap_b = self.overlap(enc.f_b, top_b, log_w_b.shape[-1], cycle_b)
        return Match(log_w_a, log_w_b, best_a, best_b, overlap_a, overlap_b)

    def generate(self, enc: Encoded, match: Match) -> GenRegOutput:
        """Stage 3: A_g (A in B's frame) and B_g (B in A's frame) from the matches."""
        if self.config.generation == "neighbours":
            # At inference the neighbours come from the encoder's graph (its first k are the k nearest);
            # training keeps its own query, as it always has.
            k, graphs = self.config.generation_k, (None, None) if self.training else (enc.knn_b, enc.knn_a)
            a_gen = neighbour_mix(match.log_w_a, match.best_a, enc.b0, k, graphs[0])
            b_gen = neighbour_mix(match.log_w_b, match.best_b, enc.a0, k, graphs[1])
        else:
            a_gen = pick(match.log_w_a, match.best_a, enc.b0, self.training)
            b_gen = pick(match.log_w_b, match.best_b, enc.a0, self.training)
        overlap = None if match.overlap_a is None else (match.overlap_a, match.overlap_b)
        return GenRegOutput(a_gen + enc.c_b, b_gen + enc.c_a, (match.log_w_a, match.log_w_b), overlap)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> GenRegOutput:
        enc = self.encode(a, b)
        return self.generate(enc, self.interact(enc))
