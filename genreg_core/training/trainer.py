"""GenReg GAN training: generator (GenRegNet) + discriminator, PDSAC in the loop (paper Sec. 3.4).

One iteration updates the discriminator; every `gan.generator_every`-th iteration also updates the
generator (the supplement's schedule is 5). Runs single-process or under `torchrun` (DDP; gloo on
CPU, nccl on GPU) without code changes. `last.ckpt` in the run folder holds everything needed to
continue exactly: models, optimisers, schedulers, iteration, RNG state and elapsed time.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from tqdm import tqdm

from genreg_core.checkpoint import load_checkpoint, save_checkpoint
from genreg_core.config import RegistrationConfig
from genreg_core.errors import CheckpointError
from genreg_core.geometry import apply_transform, invert_transform
from genreg_core.metrics import chamfer_distance, rotation_error_deg
from genreg_core.model import GenRegOutput, build_model
from genreg_core.model.discriminator import Discriminator
from genreg_core.pdsac import pdsac
from genreg_core.registration import Registrar
from genreg_core.training import losses as L
from genreg_core.training.config import TrainConfig
from genreg_core.training.datasets import build_pair_sets, make_batch, validation_batches

INFERENCE = RegistrationConfig()  # validation measures what the registration pipeline does (network + PDSAC)

LOG_FIELDS = (
    "iteration", "generator_steps", "elapsed_s", "lr", "max_angle_deg", "loss", "absolute", "relative",
    "cycle", "adversarial", "transformation", "correspondence", "matching", "overlap", "discriminator",
    "skipped_steps",
    "val_re_mean", "val_re_median", "val_te_mean", "val_cd_mean",
)


class CycleGenerator(nn.Module):
    """Both generator passes in one forward, so DDP sees one forward per backward:
    G(A, B) -> (A_g, B_g), and, when asked, the cycle G(A_g, B_g) -> back to (A, B)."""

    def __init__(self, generator: nn.Module) -> None:
        super().__init__()
        self.generator = generator

    def forward(self, a: torch.Tensor, b: torch.Tensor, cycle: bool) -> tuple[GenRegOutput, GenRegOutput | None]:
        out = self.generator(a, b)
        back = self.generator(out.source_generated, out.target_generated) if cycle else None
        return out, back


class Trainer:
    """Builds models, data and optimisers from a TrainConfig; `run()` trains to `schedule.steps`."""

    def __init__(self, cfg: TrainConfig, resume: bool = False, show_progress: bool = True) -> None:
        self.cfg = cfg
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        if self.world > 1 and not dist.is_initialized():
            dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        self.device = torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}" if torch.cuda.is_available() else "cpu")
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.out_dir = Path(cfg.out_dir)
        self.is_main = self.rank == 0
        self.show_progress = show_progress and self.is_main
        self.generator = build_model(cfg.model).to(self.device)
        self.discriminator = Discriminator(cfg.model.discriminator_hidden).to(self.device)
        self.gen_step_module: nn.Module = CycleGenerator(self.generator)
        self.disc_module: nn.Module = self.discriminator
        if self.world > 1:
            self.gen_step_module = nn.parallel.DistributedDataParallel(self.gen_step_module)
            self.disc_module = nn.parallel.DistributedDataParallel(self.discriminator)
        s = cfg.schedule
        self.opt_g = torch.optim.AdamW(self.generator.parameters(), lr=s.lr, weight_decay=s.weight_decay)
        self.opt_d = torch.optim.Adam(self.discriminator.parameters(), lr=cfg.gan.lr, betas=(0.5, 0.9))
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, self._lr_factor)
        self.train_set, self.val_set = build_pair_sets(cfg)
        self.val_batches = validation_batches(self.val_set, cfg.validation_pairs, s.batch_size)
        self.iteration = 0
        self.skipped_steps = 0  # generator updates skipped for a non-finite gradient
        self.elapsed = 0.0
        self.best_re = math.inf
        if resume and (self.out_dir / "last.ckpt").exists():
            self._load_state(self.out_dir / "last.ckpt")
            self._truncate_log()
        elif cfg.init_from:
            self._warm_start(cfg.init_from)

    def _warm_start(self, name_or_path: str) -> None:
        """Generator weights from a checkpoint (fresh optimiser). Modules the checkpoint lacks (e.g. a new
        overlap head) keep their initialisation; a weight of another shape or an unknown one is an error."""
        warm, _ = load_checkpoint(name_or_path, num_points=self.cfg.model.num_points)
        result = self.generator.load_state_dict(warm.state_dict(), strict=False)
        if result.unexpected_keys:
            raise CheckpointError(f"init_from {name_or_path}: weights this model does not have: "
                                  f"{result.unexpected_keys[:5]}")
        if self.is_main and result.missing_keys:
            print(f"init_from {name_or_path}: newly initialised: {sorted({k.split('.')[0] for k in result.missing_keys})}")

    # ----------------------------------------------------------------- schedule
    def _lr_factor(self, it: int) -> float:
        s = self.cfg.schedule
        if it < s.warmup_steps:
            return (it + 1) / s.warmup_steps
        progress = min(1.0, (it - s.warmup_steps) / max(1, s.steps - s.warmup_steps))
        return s.min_lr_ratio + (1 - s.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    def max_angle(self, it: int) -> float:
        s, d = self.cfg.schedule, self.cfg.data
        if s.curriculum_steps <= 0:
            return d.max_angle_deg
        frac = min(1.0, it / s.curriculum_steps)
        return s.curriculum_start_deg + frac * (d.max_angle_deg - s.curriculum_start_deg)

    # ----------------------------------------------------------------- one iteration
    def train_iteration(self) -> dict[str, float]:
        cfg, it = self.cfg, self.iteration
        self.train_set.max_angle_deg = self.max_angle(it)
        batch = {k: v.to(self.device) for k, v in make_batch(self.train_set, cfg, it, self.rank).items()}
        a, b, T_gt = batch["source"], batch["target"], batch["transform"]
        generator_step = it % cfg.gan.generator_every == 0
        logs: dict[str, float] = {}
        self.generator.train()
        if generator_step:
            out, back = self.gen_step_module(a, b, cfg.loss.cycle > 0)
            terms = self.generator_losses(a, b, T_gt, out, back, it)
            loss = sum(getattr(cfg.loss, k) * v for k, v in terms.items())
            self.opt_g.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(self.generator.parameters(), cfg.schedule.grad_clip)
            if torch.isfinite(grad_norm):
                self.opt_g.step()
            else:  # one bad batch must not poison the weights: skip the update, count it
                self.skipped_steps += 1
            self.sched_g.step()
            logs = {k: float(v.detach()) for k, v in terms.items()} | {"loss": float(loss.detach()),
                                                                     "skipped_steps": float(self.skipped_steps)}
            fake = torch.cat([out.source_generated, out.target_generated]).detach()
        else:
            with torch.no_grad():
                out = self.generator(a, b)
            fake = torch.cat([out.source_generated, out.target_generated])
        logs["discriminator"] = self.discriminator_update(torch.cat([b, a]), fake)
        self.iteration += 1
        return logs

    def generator_losses(
        self, a: torch.Tensor, b: torch.Tensor, T_gt: torch.Tensor, out: GenRegOutput,
        back: GenRegOutput | None, it: int,
    ) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        a_g, b_g = out.source_generated, out.target_generated
        subset_gen = torch.Generator().manual_seed(cfg.seed * 7919 + it)

        def emd(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            x, y = L.random_subset(x, cfg.emd_points, subset_gen), L.random_subset(y, cfg.emd_points, subset_gen)
            return L.sinkhorn_emd(x, y, cfg.emd_epsilon, cfg.emd_iterations).mean()

        zero = a.new_zeros(())
        terms = {
            "absolute": emd(b, a_g) + emd(a, b_g) if cfg.loss.absolute > 0 else zero,
            "relative": (L.relative_loss(a, a_g) + L.relative_loss(b, b_g)).mean(),
            "cycle": emd(back.source_generated, a) + emd(back.target_generated, b) if back is not None else zero,
        }
        fake_logits = self.disc_module(torch.cat([a_g, b_g]))
        terms["adversarial"] = (
            -fake_logits.mean() if cfg.gan.mode == "wgan-gp" else L.gan_generator_loss(fake_logits)
        )
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + it)
        T_inv = invert_transform(T_gt)
        a_true, b_true = apply_transform(T_gt, a), apply_transform(T_inv, b)  # A in B's frame, B in A's
        over_a = L.overlap_labels(a_true, b, cfg.loss.overlap_radius)  # points with a counterpart
        over_b = L.overlap_labels(b_true, a, cfg.loss.overlap_radius)
        o_a, o_b = out.overlap() or (None, None)
        res_a = pdsac(a, a_g, cfg.pdsac, gen, refit=False, weights=o_a)
        res_b = pdsac(b, b_g, cfg.pdsac, gen, refit=False, weights=o_b)
        terms["transformation"] = (
            L.expected_transformation_loss(res_a.hypotheses, res_a.weights, T_gt)
            + L.expected_transformation_loss(res_b.hypotheses, res_b.weights, T_inv)
        ).mean()
        terms["correspondence"] = (L.masked_mean((a_g - a_true).abs().sum(-1), over_a)
                                   + L.masked_mean((b_g - b_true).abs().sum(-1), over_b)).mean()
        terms["matching"] = zero
        if cfg.loss.matching > 0 and out.match_logits is not None:
            log_w_a, log_w_b = out.match_logits
            c_a, c_b = a.mean(1, keepdim=True), b.mean(1, keepdim=True)  # the pointer works on centred clouds
            sigma = cfg.loss.matching_sigma
            terms["matching"] = (L.matching_loss(log_w_a, a_true - c_b, b - c_b, sigma, over_a)
                                 + L.matching_loss(log_w_b, b_true - c_a, a - c_a, sigma, over_b)).mean()
        terms["overlap"] = zero
        if out.overlap_logits is not None:
            logit_a, logit_b = out.overlap_logits
            terms["overlap"] = (nn.functional.binary_cross_entropy_with_logits(logit_a, over_a.to(a.dtype))
                                + nn.functional.binary_cross_entropy_with_logits(logit_b, over_b.to(b.dtype)))
        return terms

    def discriminator_update(self, real: torch.Tensor, fake: torch.Tensor) -> float:
        cfg = self.cfg
        real_logits, fake_logits = self.disc_module(torch.cat([real, fake])).chunk(2)
        if cfg.gan.mode == "wgan-gp":
            loss = fake_logits.mean() - real_logits.mean()
            loss = loss + cfg.gan.gradient_penalty * L.wgan_gradient_penalty(self.discriminator, real, fake)
        else:
            loss = L.gan_discriminator_loss(real_logits, fake_logits)
        self.opt_d.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_d.step()
        return float(loss.detach())

    # ----------------------------------------------------------------- validation
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """RE/TE/CD of network + PDSAC with the pipeline's own settings (`Registrar.estimate`: hard
        selection, refit) on the fixed validation pairs."""
        registrar = Registrar(self.generator, INFERENCE)  # puts the generator in eval mode
        re, te, cd = [], [], []
        gen = torch.Generator().manual_seed(self.cfg.seed)
        for batch in self.val_batches:
            a, b, T_gt = (batch[k].to(self.device) for k in ("source", "target", "transform"))
            T_est = registrar.estimate(a, b, gen).transform
            for i in range(len(a)):
                Te, Tg = T_est[i].double().cpu().numpy(), T_gt[i].double().cpu().numpy()
                re.append(rotation_error_deg(Te[:3, :3], Tg[:3, :3]))
                te.append(float(np.linalg.norm(Te[:3, 3] - Tg[:3, 3])))
                cd.append(chamfer_distance(apply_transform(Te, a[i].double().cpu().numpy()), b[i].cpu().numpy()))
        return {"val_re_mean": float(np.mean(re)), "val_re_median": float(np.median(re)),
                "val_te_mean": float(np.mean(te)), "val_cd_mean": float(np.mean(cd))}

    # ----------------------------------------------------------------- state
    def _state(self) -> dict:
        return {
            "generator": self.generator.state_dict(), "discriminator": self.discriminator.state_dict(),
            "opt_g": self.opt_g.state_dict(), "opt_d": self.opt_d.state_dict(),
            "sched_g": self.sched_g.state_dict(), "iteration": self.iteration, "elapsed": self.elapsed,
            "best_re": self.best_re, "torch_rng": torch.get_rng_state(), "skipped_steps": self.skipped_steps,
            "config": _plain(dataclasses.asdict(self.cfg)),
        }

    def _load_state(self, path: Path) -> None:
        state = torch.load(path, map_location=self.device, weights_only=True)
        self.generator.load_state_dict(state["generator"])
        self.discriminator.load_state_dict(state["discriminator"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.opt_d.load_state_dict(state["opt_d"])
        self.sched_g.load_state_dict(state["sched_g"])
        self.iteration, self.elapsed, self.best_re = state["iteration"], state["elapsed"], state["best_re"]
        torch.set_rng_state(state["torch_rng"])
        self.skipped_steps = int(state.get("skipped_steps", 0))

    def save(self) -> None:
        """Atomically write last.ckpt (full state, stays out of git) and last.pt (fp16 weights)."""
        if not self.is_main:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.out_dir / "last.ckpt.tmp"
        torch.save(self._state(), tmp)
        os.replace(tmp, self.out_dir / "last.ckpt")
        save_checkpoint(self.generator, self.out_dir / "last.pt", self._meta())

    def _meta(self) -> dict:
        return {"iteration": self.iteration, "elapsed_s": round(self.elapsed, 1), "name": self.cfg.name,
                "best_val_re_mean": self.best_re}

    # ----------------------------------------------------------------- loop
    def run(self, max_iterations: int | None = None, max_seconds: float | None = None) -> dict[str, float]:
        """Train until `schedule.steps` (or the given limits); returns the last validation metrics."""
        cfg = self.cfg
        end = cfg.schedule.steps if max_iterations is None else min(cfg.schedule.steps, self.iteration + max_iterations)
        bar = tqdm(total=end, initial=self.iteration, disable=not self.show_progress, dynamic_ncols=True)
        start_wall, start_elapsed = time.perf_counter(), self.elapsed
        running: dict[str, float] = {}
        val: dict[str, float] = {}
        while self.iteration < end:
            logs = self.train_iteration()
            self.elapsed = start_elapsed + time.perf_counter() - start_wall
            for k, v in logs.items():
                running[k] = v if k not in running or k == "skipped_steps" else 0.9 * running[k] + 0.1 * v
            bar.update(1)
            bar.set_postfix({k: f"{running[k]:.3g}" for k in ("loss", "transformation", "discriminator") if k in running})
            it = self.iteration
            if self.is_main and (it % cfg.validate_every == 0 or it == end):
                val = self.validate()
                if val["val_re_mean"] < self.best_re:
                    self.best_re = val["val_re_mean"]
                    save_checkpoint(self.generator, self.out_dir / "best.pt", self._meta())
                bar.write(f"iteration {it}: " + ", ".join(f"{k} {v:.4g}" for k, v in val.items()))
            if it % cfg.log_every == 0 or val:
                self._log(running, val)
            if it % cfg.checkpoint_every == 0 or it == end:
                self.save()
            val = {}
            if max_seconds is not None and self._all_agree(time.perf_counter() - start_wall > max_seconds):
                self.save()
                break
        bar.close()
        val = val or (self.validate() if self.is_main else {})
        if self.world > 1:
            dist.barrier()  # no rank leaves while rank 0 still validates and saves
        return val

    def _all_agree(self, flag: bool) -> bool:
        """True on every rank when `flag` is true on any (ranks must stop at the same iteration)."""
        if self.world == 1:
            return flag
        value = torch.tensor([float(flag)])
        dist.all_reduce(value, op=dist.ReduceOp.MAX)
        return bool(value.item())

    def _truncate_log(self) -> None:
        """Drop log rows written after the checkpoint we resume from, so the curve has no repeats."""
        path = self.out_dir / "log.csv"
        if not self.is_main or not path.exists():
            return
        with path.open() as f:
            rows = list(csv.DictReader(f))
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=LOG_FIELDS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(r for r in rows if int(r["iteration"]) <= self.iteration)

    def _log(self, running: dict[str, float], val: dict[str, float]) -> None:
        if not self.is_main:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        path = self.out_dir / "log.csv"
        new = not path.exists()
        row = {"iteration": self.iteration, "generator_steps": self.iteration // self.cfg.gan.generator_every,
               "elapsed_s": round(self.elapsed, 2), "lr": self.sched_g.get_last_lr()[0],
               "max_angle_deg": self.train_set.max_angle_deg} | running | val
        with path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=LOG_FIELDS, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow(row)


def _plain(value: object) -> object:
    """Tuples to lists (recursively) so the config stores under weights_only loading."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
