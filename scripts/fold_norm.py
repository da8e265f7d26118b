#!/usr/bin/env python3
"""Make a GenReg checkpoint statistics-free, the warm start of a crop-robust model.

    git show 4aa431f:genreg_core/weights/modelnet40_partial.pt > prev.pt   # the GroupNorm partial model
    python scripts/fold_norm.py prev.pt runs/modelnet40_local_init.pt --pairs 150
    python scripts/fold_norm.py modelnet40_dgcnn runs/modelnet40_dgcnn_local_init.pt --kind objects

Why and how: `genreg_core.model.fold`. This script measures the average statistics on pairs of the
ModelNet40 *train* split (seen categories): RPM-Net-style crops (seed 5; `--kind crops`, the partial model's)
or the object model's training pairs, clean, noise and one-side partial mixed (seed 11; `--kind objects`).
It folds them and writes the checkpoint (`norm: none`, `pointer_centring: false`), and prints the accuracy of
both models alone on 100 other training pairs of the same kind (seed 2): crops, about equal before
fine-tuning (25.71 / 2.02 deg, 69 % against 23.75 / 2.16, 69 %).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="shipped name or file, GroupNorm model")
    p.add_argument("out", type=Path, help="checkpoint file to write (fp32)")
    p.add_argument("--pairs", type=int, default=150, help="training pairs the statistics are averaged over")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--kind", choices=("crops", "objects"), default="crops", help="the pairs measured on")
    args = p.parse_args()
    from genreg_bench.cli import configure_threads

    configure_threads(args.threads)
    import numpy as np
    import torch
    from torch import nn
    from tqdm import tqdm

    from genreg_bench.datasets import RPMNetPairs
    from genreg_core.checkpoint import load_checkpoint, save_checkpoint
    from genreg_core.config import RefineConfig, RegistrationConfig
    from genreg_core.data import ModelNetPairs, load_modelnet40
    from genreg_core.metrics import transform_errors
    from genreg_core.model.fold import NormStatistics, fold_statistics
    from genreg_core.registration import Registrar

    model, meta = load_checkpoint(args.checkpoint)
    if model.config.backbone != "dgcnn":
        raise SystemExit("fold_norm.py: the pointer's centres are measured through backbone 'dgcnn''s linear layer")
    shapes = load_modelnet40("train", "seen")
    cfg = RegistrationConfig(seed=0, refine=RefineConfig(method="none"))

    def training_pairs(seed: int, n: int) -> list[dict]:
        """n training pairs of the chosen kind."""
        pairs = RPMNetPairs(shapes, seed=seed) if args.kind == "crops" else ModelNetPairs(
            shapes, 512, ("clean", "noise", "partial"), seed=seed)
        return [pairs[int(i)] for i in np.random.default_rng(seed).choice(len(pairs), n, replace=False)]

    def accuracy(net: nn.Module) -> str:
        registrar = Registrar(net, cfg)
        re = np.array([transform_errors(registrar.register(it["source"], it["target"]).transformation,
                                        it["transform"])[0] for it in tqdm(training_pairs(2, 100), desc="evaluate")])
        return f"RE mean {re.mean():.2f} deg, median {np.median(re):.2f}, {np.mean(re < 5):.0%} under 5 deg"

    # 1. average statistics: per group mean and variance of each GroupNorm input, queries' and keys' means
    seen: dict[str, list[torch.Tensor]] = {}

    def record(name: str, value: torch.Tensor) -> None:
        seen.setdefault(name, []).append(value.detach())

    def group_moments(mod: nn.GroupNorm, x: torch.Tensor) -> torch.Tensor:  # (B, 2, groups)
        grouped = x.reshape(x.shape[0], mod.num_groups, -1)
        return torch.stack([grouped.mean(-1), grouped.var(-1, unbiased=False)], dim=1)

    hooks = [m.register_forward_hook(lambda mod, inp, _out, name=name: record(name, group_moments(mod, inp[0])))
             for name, m in model.named_modules() if isinstance(m, nn.GroupNorm)]
    def centres(_module: nn.Module, _inputs: tuple, h: torch.Tensor) -> None:
        """The pointer's query and key centres of each cloud, from its GCNN features h (B, N, C): the maps
        from h to them are affine (the backbone's linear layer, then the projections; inference folds them
        into one product, `GenRegNet.first_products`, so the projections never run as modules)."""
        f = model.encoder.mixer1(h.mean(dim=1))
        record("query", model.pointer.query(f))
        record("key", model.pointer.key(f))

    hooks.append(model.encoder.gcnn.register_forward_hook(centres))
    registrar = Registrar(model, cfg)
    for item in tqdm(training_pairs(5 if args.kind == "crops" else 11, args.pairs), desc="statistics"):
        registrar.register(item["source"], item["target"])
    for h in hooks:
        h.remove()
    mean = {name: torch.cat(v).mean(dim=0) for name, v in seen.items()}
    query, key = mean.pop("query"), mean.pop("key")

    # 2. fold them into the layers (genreg_core.model.fold)
    local = fold_statistics(model, NormStatistics({n: (m[0], m[1]) for n, m in mean.items()}, query, key))

    print(f"{args.checkpoint} (GroupNorm): {accuracy(model)}")
    print(f"statistics-free: {accuracy(local)}")
    save_checkpoint(local, args.out, half=False, meta={**meta, "folded_from": str(args.checkpoint)})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
