"""`genreg-train`: train GenReg from a YAML config, resumable; works under torchrun.

    genreg-train --config config/train_modelnet40_ppf.yaml            # fresh run into out_dir
    genreg-train --config config/train_modelnet40_ppf.yaml --resume  # continue exactly from last.ckpt
    torchrun --standalone --nproc_per_node 2 -m genreg_core.training.cli --config ...   # DDP (gloo on CPU)
"""

from __future__ import annotations

import argparse
import sys

import torch.distributed as dist
import yaml

from genreg_core.errors import GenRegError
from genreg_core.memory import retain_freed_memory
from genreg_core.training.config import load_train_config
from genreg_core.training.trainer import Trainer


def parse_overrides(items: list[str]) -> dict:
    """`a.b=value` strings -> nested dict; values parsed as YAML scalars."""
    out: dict = {}
    for item in items:
        key, _, value = item.partition("=")
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = yaml.safe_load(value)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="genreg-train", description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="training YAML (see config/train_*.yaml)")
    parser.add_argument("--resume", action="store_true", help="continue from <out_dir>/last.ckpt if present")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="override config keys")
    parser.add_argument("--max-iterations", type=int, default=None, help="stop after this many iterations")
    parser.add_argument("--max-seconds", type=float, default=None, help="stop (with a checkpoint) after this time")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    retain_freed_memory()  # genreg_core.memory: a third of training's CPU time went to page faults
    try:
        cfg = load_train_config(args.config, parse_overrides(args.set))
        trainer = Trainer(cfg, resume=args.resume, show_progress=not args.no_progress)
        metrics = trainer.run(args.max_iterations, args.max_seconds)
    except (GenRegError, FileNotFoundError, yaml.YAMLError) as exc:
        print(f"genreg-train: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
    if trainer.is_main:
        print("final validation: " + ", ".join(f"{k} {v:.4g}" for k, v in metrics.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
