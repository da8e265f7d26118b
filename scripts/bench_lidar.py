"""Synthetic LiDAR scans under kidnap motions: the node's scene profile, and Open3D FPFH + RANSAC + ICP.

Pairs (`genreg_core.data.synthetic_lidar`): a target scan at a random pose in the scene's free space, a
source scan 0.5-1 m away (up to 10 deg of yaw), the source points then moved about their centroid by a
kidnap of up to --max-angle deg (mostly yaw) and --max-translation m. Truth: T_target_source composed
from the poses and the kidnap. Success: RE < 2 deg and TE < 0.3 m. Each pair runs in three variants:

    lidar        the scans as emitted, with their dual returns (4 % of the points twice)
    dedup        the same scans without duplicate points (np.unique)
    dedup+5%dup  the deduplicated scans with 5 % of their points duplicated (appended copies)

GenReg runs with the node's scene profile (config/genreg.yaml: model 7scenes, GICP, PDSAC sample size 4);
FPFH + RANSAC + ICP (`genreg_bench.baselines.fpfh_ransac_icp`, Open3D) on the `lidar` variant, with
the RGB-D scene settings scaled to the scene (x3 room: 15 cm feature voxels; x6 street: 30 cm). A pair whose
registration raises counts as a failure; the exceptions are counted in the table.

    python scripts/bench_lidar.py --pairs 50 --scene both --seed 0 --threads 1
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=50, help="pairs per scene")
    p.add_argument("--scene", choices=("room", "street", "both"), default="both")
    p.add_argument("--seed", type=int, default=0, help="pairs' seed (the scene layouts are fixed, seed 0)")
    p.add_argument("--threads", type=int, default=1, help="torch, Open3D (OMP_NUM_THREADS) and small_gicp threads")
    p.add_argument("--beams", type=int, default=0, help="uniform beams over -25..+15 deg (0: the default sensor)")
    p.add_argument("--columns", type=int, default=1024, help="azimuth steps with --beams")
    p.add_argument("--max-angle", type=float, default=45.0, help="kidnap rotation bound, deg")
    p.add_argument("--max-translation", type=float, default=2.0, help="kidnap translation bound, m")
    p.add_argument("--no-baseline", action="store_true", help="skip FPFH + RANSAC + ICP")
    return p.parse_args()


ARGS = parse()
os.environ["OMP_NUM_THREADS"] = str(ARGS.threads)  # before Open3D and torch load

import numpy as np
import torch
from tqdm import tqdm

from genreg_bench.baselines import BaselineParams, fpfh_ransac_icp
from genreg_core.config import SCENE_MODEL, SCENE_REGISTRATION
from genreg_core.data.synthetic_lidar import (
    LidarSensor,
    default_sensor,
    kidnap,
    lidar_scan,
    make_scene,
    nearby_pose,
    random_sensor_pose,
)
from genreg_core.geometry import apply_transform
from genreg_core.metrics import transform_errors
from genreg_core.registration import Registrar

MAX_RE_DEG, MAX_TE_M = 2.0, 0.3
BASELINE_SCALE = {"room": 3.0, "street": 6.0}


def make_pairs(scene_name: str, n: int, seed: int, sensor: LidarSensor
               ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
    """(source, target, T_target_source, kidnap angle deg) per pair; source and target as emitted."""
    scene = make_scene(scene_name)
    rng = np.random.default_rng(seed)
    pairs = []
    for _ in tqdm(range(n), desc=f"{scene_name} scans", unit="pair", file=sys.stderr):
        pose_t = random_sensor_pose(scene_name, rng)
        pose_s = nearby_pose(pose_t, rng)
        target = lidar_scan(scene, pose_t, rng, sensor).points
        source = lidar_scan(scene, pose_s, rng, sensor).points.astype(np.float64)
        K = kidnap(rng, source.mean(0), ARGS.max_angle, ARGS.max_translation)
        angle = float(np.degrees(np.arccos(np.clip((np.trace(K[:3, :3]) - 1) / 2, -1, 1))))
        pairs.append((apply_transform(K, source).astype(np.float32), target,
                      np.linalg.inv(pose_t) @ pose_s @ np.linalg.inv(K), angle))
    return pairs


def with_duplicates(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """Deduplicated points plus exact copies of `share` of them."""
    unique = np.unique(points, axis=0)
    return np.concatenate([unique, unique[rng.choice(len(unique), round(share * len(unique)), replace=False)]])


def variants(source: np.ndarray, target: np.ndarray, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {"lidar": (source, target),
            "dedup": (np.unique(source, axis=0), np.unique(target, axis=0)),
            "dedup+5%dup": (with_duplicates(source, 0.05, rng), with_duplicates(target, 0.05, rng))}


class Tally:
    """Errors and times of one method on one variant."""

    def __init__(self) -> None:
        self.re: list[float] = []
        self.te: list[float] = []
        self.ms: list[float] = []
        self.angles: list[float] = []
        self.errors: dict[str, int] = {}

    def add(self, run, truth: np.ndarray, angle: float) -> None:  # run: () -> 4x4
        t0 = time.perf_counter()
        try:
            T = run()
        except Exception as e:  # noqa: BLE001 (any crash is a failed pair, counted by its type)
            name = type(e).__name__
            self.errors[name] = self.errors.get(name, 0) + 1
            self.re.append(np.inf), self.te.append(np.inf), self.angles.append(angle)
            return
        self.ms.append(1000 * (time.perf_counter() - t0))
        re, te = transform_errors(T, truth)
        self.re.append(re), self.te.append(te), self.angles.append(angle)

    def row(self, label: str) -> str:
        re, te = np.asarray(self.re), np.asarray(self.te)
        ok = (re < MAX_RE_DEG) & (te < MAX_TE_M)
        fin = np.isfinite(re)
        big = np.asarray(self.angles) > 30
        errors = " ".join(f"{k}x{v}" for k, v in self.errors.items()) or "-"
        return (f"{label:<24} {ok.sum():>3}/{len(ok):<3} {100 * ok.mean():5.1f}%  "
                f"{np.mean(re[fin]) if fin.any() else np.nan:7.2f} {np.median(re):6.2f}  "
                f"{np.mean(te[fin]) if fin.any() else np.nan:7.3f} {np.median(te):6.3f}  "
                f"{np.median(self.ms) if self.ms else np.nan:6.0f}  "
                f"{ok[big].sum()}/{big.sum()}  {errors}")


def main() -> int:
    torch.set_num_threads(ARGS.threads)
    cfg = SCENE_REGISTRATION  # the node's scene profile (config/genreg.yaml is generated from it)
    registrar = Registrar.from_checkpoint(SCENE_MODEL, cfg)
    load = os.getloadavg()
    print(f"bench_lidar: model {SCENE_MODEL}, refine {cfg.refine.method} x{cfg.refine.max_iterations}, "
          f"PDSAC sample size {cfg.pdsac.sample_size}, estimate_threads {cfg.estimate_threads}")
    print(f"threads: torch {torch.get_num_threads()}, OMP_NUM_THREADS {os.environ.get('OMP_NUM_THREADS')}; "
          f"cpus {os.cpu_count()}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"pairs {ARGS.pairs} per scene, seed {ARGS.seed}, kidnap <= {ARGS.max_angle:g} deg and "
          f"{ARGS.max_translation:g} m; success RE < {MAX_RE_DEG:g} deg and TE < {MAX_TE_M:g} m")
    scenes = ("room", "street") if ARGS.scene == "both" else (ARGS.scene,)
    for scene_name in scenes:
        sensor = default_sensor(scene_name) if ARGS.beams == 0 else LidarSensor.uniform(
            ARGS.beams, (-25.0, 15.0), ARGS.columns, max_range=default_sensor(scene_name).max_range)
        pairs = make_pairs(scene_name, ARGS.pairs, ARGS.seed, sensor)
        baseline = BaselineParams.metric_scene(ARGS.threads).scaled(BASELINE_SCALE[scene_name])
        tallies: dict[str, Tally] = {}
        rng = np.random.default_rng(ARGS.seed + 1)
        for source, target, truth, angle in tqdm(pairs, desc=f"{scene_name} registration", unit="pair", file=sys.stderr):
            for name, (s, t) in variants(source, target, rng).items():
                tallies.setdefault(f"GenReg {name}", Tally()).add(
                    lambda s=s, t=t: registrar.register(s, t).transformation, truth, angle)
            if not ARGS.no_baseline:
                tallies.setdefault("FPFH+RANSAC+ICP lidar", Tally()).add(
                    lambda s=source, t=target, b=baseline: fpfh_ransac_icp(s.astype(np.float64), t.astype(np.float64), b)[0],
                    truth, angle)
        points = np.mean([len(p[0]) for p in pairs])
        print(f"\n{scene_name}: {sensor.beams} beams x {sensor.columns} columns, max range {sensor.max_range:g} m, "
              f"{points:.0f} points per scan (mean)")
        print(f"{'method / variant':<24} {'success':>12}  {'RE mean median':>14}  {'TE mean median':>14}  "
              f"{'ms p50':>6}  >30deg  errors")
        for label, tally in tallies.items():
            print(tally.row(label))
    return 0


if __name__ == "__main__":
    sys.exit(main())
