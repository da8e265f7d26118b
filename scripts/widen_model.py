#!/usr/bin/env python3
"""Widen a statistics-free GenReg checkpoint without changing what it computes: the warm start of the
capacity lever for partial overlap (`genreg_core.model.fold.widen`).

    python scripts/widen_model.py modelnet40_partial runs/modelnet40_wide_init.pt --gcnn-channels 128 --feature-dim 256

It checks the widened network against the original on one ModelNet40 training crop and writes it fp32.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="shipped name or file (statistics-free, backbone dgcnn)")
    p.add_argument("out", type=Path, help="checkpoint file to write (fp32)")
    p.add_argument("--gcnn-channels", type=int, default=128)
    p.add_argument("--feature-dim", type=int, default=256)
    args = p.parse_args()
    import torch

    from genreg_bench.datasets import RPMNetPairs
    from genreg_core.checkpoint import load_checkpoint, save_checkpoint
    from genreg_core.data import load_modelnet40
    from genreg_core.model.fold import widen

    model, meta = load_checkpoint(args.checkpoint)  # float32, eval mode
    wide = widen(model, args.gcnn_channels, args.feature_dim)
    item = RPMNetPairs(load_modelnet40("train", "seen"), seed=5)[0]
    n = model.config.num_points
    a = torch.as_tensor(item["source"][None, :n], dtype=torch.float32)
    b = torch.as_tensor(item["target"][None, :n], dtype=torch.float32)
    with torch.inference_mode():
        gap = (model(a, b).source_generated - wide(a, b).source_generated).abs().max().item()
    params = sum(t.numel() for t in model.parameters()), sum(t.numel() for t in wide.parameters())
    print(f"parameters {params[0]} -> {params[1]}; largest change of A_g on a training crop: {gap:.2e}")
    save_checkpoint(wide, args.out, half=False, meta={**meta, "widened_from": str(args.checkpoint)})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
