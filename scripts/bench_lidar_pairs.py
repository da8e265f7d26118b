"""LiDAR scans metres apart in a synthetic campus, registered pair by pair: the shipped pair-mode profiles and
the baselines on the same pairs.

Pairs (`genreg_core.data.lidar_world`, the campus of --seed: worlds 0 and 1 are the training campuses, 7, 13
and 19 held out): scans along the longest street (`bench_lidar_map.py`'s drive, 1 m steps) `--road` metres apart
and along the main corridor (its walk, 0.15 m steps) `--corridor` metres apart, each scan with its own movers;
the source turned about its sensor's z axis by a yaw uniform in +-180 deg (a robot that does not know its
heading). Truth: T_target_source from the poses and the turn. Right: RE < 2 deg and TE < 0.3 m; accepted:
confidence >= 0.5; confidently wrong: accepted and not right (the baselines give no confidence: right only).

Methods, on the same pairs:
    genreg.yaml           the scene profile on the raw scans (what a new user runs first)
    genreg_lidar.yaml     the LiDAR pair profile: scans voxelised to 0.5 m, a pose as well fitted slid along the
                          scan's main axis held (`registration.slide_fit`)
    fpfh+ransac+icp       Open3D, the scene settings scaled x6 (30 cm features), as bench_lidar.py's street
    kiss-matcher+p2plane  KISS-Matcher at the same scale, then point-to-plane ICP
(the baselines on the first --baseline-pairs pairs of each distance). Then, an outside check on real scans:
libpointmatcher's car pair (`$GENREG_DATA/lidar/libpointmatcher_car`, held out: never tuned on), scan 401 in scan
400 with the source turned about its z axis by 0, 45, ..., 315 deg (as recorded: 14.6 deg and 0.2 m apart).

    python scripts/bench_lidar_pairs.py --seed 7 13 19 --pairs 10 --baseline-pairs 3 --plot docs/lidar_pairs.png
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, nargs="+", default=[7], help="campus worlds (0, 1: training; 7, 13, 19: held "
                   "out); with several, each one's tables and then all of them together")
    p.add_argument("--pairs", type=int, default=10, help="pairs per distance")
    p.add_argument("--road", type=str, default="3,6,9,12,15,20", help="distances along the street, m")
    p.add_argument("--corridor", type=str, default="0.5,1,2,4,8", help="distances along the corridor, m")
    p.add_argument("--baseline-pairs", type=int, default=0, help="pairs per distance for the baselines (0: none)")
    p.add_argument("--threads", type=int, default=2, help="torch, Open3D (OMP_NUM_THREADS) and small_gicp threads")
    p.add_argument("--out", type=Path, default=None, help="directory for results.json")
    p.add_argument("--plot", type=Path, default=None, help="draw accepted right and confidently wrong against the "
                   "distance, every campus together, to this PNG (e.g. docs/lidar_pairs.png)")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


ARGS = parse() if __name__ == "__main__" else parse([])
os.environ["OMP_NUM_THREADS"] = str(ARGS.threads)  # before Open3D and torch load
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_lidar_map import WALK_STEP, drive_poses, walk_poses

from genreg_bench.baselines import BaselineParams, fpfh_ransac_icp, kiss_matcher_p2plane
from genreg_core.config import data_root
from genreg_core.data import lidar_world as lw
from genreg_core.data.synthetic_lidar import sensor_pose
from genreg_core.geometry import apply_transform
from genreg_core.metrics import transform_errors
from genreg_core.preprocess import preprocess
from genreg_core.registration import Registrar
from genreg_ros.config import profile_config

MAX_RE_DEG, MAX_TE_M, GATE = 2.0, 0.3, 0.5
PROFILES = ("genreg.yaml", "genreg_lidar.yaml")
BASELINES = {"fpfh+ransac+icp": fpfh_ransac_icp, "kiss-matcher+p2plane": kiss_matcher_p2plane}
POSES = 200  # scans along each path


def pairs(world: lw.World, kind: str, distances: list[float], n: int, seed: int
          ) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
    """(distance, source, target, T_target_source) per pair: `n` per distance along the street ("road") or the
    main corridor ("corridor"), the source turned about its z axis by a uniform yaw."""
    poses = drive_poses(world, POSES) if kind == "road" else walk_poses(world, POSES)
    step = 1.0 if kind == "road" else WALK_STEP
    rng = np.random.default_rng([seed, 0 if kind == "road" else 1])
    scans: dict[int, np.ndarray] = {}

    def scan(i: int) -> np.ndarray:
        if i not in scans:
            scans[i] = lw.world_scan(world, poses[i], np.random.default_rng([seed, 2, i])).points.astype(np.float64)
        return scans[i]

    out = []
    for d in distances:
        gap = round(d / step)
        for _ in range(n):
            i = int(rng.integers(0, POSES - gap))
            K = sensor_pose(0.0, 0.0, 0.0, rng.uniform(-np.pi, np.pi))  # a turn about z
            out.append((d, apply_transform(K, scan(i + gap)), scan(i),
                        np.linalg.inv(poses[i]) @ poses[i + gap] @ np.linalg.inv(K)))
    return out


def car_pairs() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(source, target, T_target_source): libpointmatcher's car scan 401 in scan 400, the source turned about its z
    axis by 0, 45, ..., 315 deg; empty when the data is missing."""
    folder = data_root() / "lidar" / "libpointmatcher_car"
    if not folder.is_dir():
        return []
    target = np.loadtxt(folder / "car_cloud400.csv", delimiter=",", skiprows=1, usecols=(0, 1, 2))
    source = np.loadtxt(folder / "car_cloud401.csv")
    poses = np.loadtxt(folder / "carCloudList.csv", delimiter=",", skiprows=1, usecols=range(1, 17))
    T = np.linalg.inv(poses[0].reshape(4, 4)) @ poses[1].reshape(4, 4)  # 401 -> 400
    return [(apply_transform(K, source), target, T @ np.linalg.inv(K)) for K in (sensor_pose(0.0, 0.0, 0.0, np.radians(a)) for a in range(0, 360, 45))]


def run(method: str, fn: Any, source: np.ndarray, target: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """One method on one pair: errors, confidence (NaN for the baselines), milliseconds."""
    t0 = time.perf_counter()
    T, confidence, named = fn(source, target)
    ms = 1000 * (time.perf_counter() - t0)
    re, te = transform_errors(T, truth)
    return {"method": method, "re": re, "te": te, "confidence": confidence, "ms": ms, "unconstrained": named}


def counts(rs: list[dict[str, Any]]) -> tuple[int, int, int]:
    """(right, accepted right, confidently wrong) of some records (a baseline's NaN confidence: never accepted)."""
    right = [r["re"] < MAX_RE_DEG and r["te"] < MAX_TE_M for r in rs]
    sure = [r["confidence"] >= GATE for r in rs]
    return sum(right), sum(a and b for a, b in zip(right, sure, strict=True)), sum(b and not a for a, b in
                                                                                  zip(right, sure, strict=True))


def table(records: list[dict[str, Any]], kind: str, distances: list[float], methods: list[str], title: str) -> None:
    """One table: per method and distance, right / accepted right / confidently wrong of n and the median ms."""
    print(f"\n{title}: pairs d m apart; right / accepted right / confidently wrong of n, median ms")
    print(f"{'method':<22}" + "".join(f"{d:>22g}" for d in distances))
    for name in methods:
        cells = []
        for d in distances:
            rs = [r for r in records if r["kind"] == kind and r["distance"] == d and r["method"] == name]
            right, accepted, wrong = counts(rs) if rs else (0, 0, 0)
            cells.append(f"{right:>4}/{accepted:>2}/{wrong:>2} of {len(rs):<3}{np.median([r['ms'] for r in rs]):>5.0f} ms"
                         if rs else f"{'-':>22}")
        print(f"{name:<22}" + "".join(cells))


def plot(path: Path, records: list[dict[str, Any]], seeds: list[int]) -> None:
    """Accepted right and confidently wrong against the distance, street and corridor side by side, every campus
    together (the baselines: right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    for ax, kind, title in zip(axes, ("road", "corridor"), ("along a street", "along a corridor"), strict=True):
        for name, colour in zip([*PROFILES, *BASELINES], ("tab:grey", "tab:blue", "tab:orange", "tab:green"), strict=True):
            rs = [r for r in records if r["kind"] == kind and r["method"] == name]
            ds = sorted({r["distance"] for r in rs})
            share = [[c / len(group) for c in counts(group)] for group in
                     ([r for r in rs if r["distance"] == d] for d in ds)]
            if name in BASELINES:
                ax.plot(ds, [x[0] for x in share], ":", marker="s", color=colour, label=f"{name}: right")
                continue
            ax.plot(ds, [x[1] for x in share], "-", marker="o", color=colour, label=f"{name}: accepted right")
            ax.plot(ds, [x[2] for x in share], "--", marker="x", color=colour, label=f"{name}: confidently wrong")
        ax.set_title(f"LiDAR scans {title}, the source turned by any yaw")
        ax.set_xlabel("distance between the scans, m")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"share of pairs (campuses {', '.join(map(str, seeds))})")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=3)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> int:
    torch.set_num_threads(ARGS.threads)
    methods: dict[str, Any] = {}
    for name in PROFILES:
        config = profile_config(name)
        registrar = Registrar.from_checkpoint(config.model.checkpoint, config.registration_config())

        def genreg(s: np.ndarray, t: np.ndarray, r: Registrar = registrar, c: Any = config) -> tuple:
            result = r.register(preprocess(s, c.preprocess), preprocess(t, c.preprocess))
            return result.transformation, result.confidence, list(result.unconstrained)

        methods[name] = genreg
    params = BaselineParams.metric_scene(ARGS.threads).scaled(6.0)
    for name, fn in BASELINES.items():
        methods[name] = lambda s, t, f=fn: (f(s, t, params)[0], float("nan"), [])
    load = os.getloadavg()
    print(f"bench_lidar_pairs: campus worlds {', '.join(map(str, ARGS.seed))}, {ARGS.pairs} pairs per distance, source "
          f"turned by any yaw; threads {ARGS.threads} (torch {torch.get_num_threads()}, OMP_NUM_THREADS "
          f"{os.environ['OMP_NUM_THREADS']}); cpus {os.cpu_count()}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    records: list[dict[str, Any]] = []
    paths = [(kind, [float(d) for d in text.split(",") if d]) for kind, text in (("road", ARGS.road),
                                                                                  ("corridor", ARGS.corridor))]
    for seed in ARGS.seed:
        world = lw.campus_world(seed)
        for kind, distances in paths:
            todo = pairs(world, kind, distances, ARGS.pairs, seed)
            for name in PROFILES:  # first calls (numba, torch, small_gicp) out of the timings
                methods[name](*todo[0][1:3])
            done: dict[float, int] = {}
            for d, source, target, truth in tqdm(todo, desc=f"campus {seed}, {kind}", unit="pair",
                                                 disable=ARGS.no_progress, file=sys.stderr):
                done[d] = done.get(d, 0) + 1
                for name, fn in methods.items():
                    if name in BASELINES and done[d] > ARGS.baseline_pairs:
                        continue
                    records.append({"seed": seed, "kind": kind, "distance": d, **run(name, fn, source, target, truth)})
            table([r for r in records if r["seed"] == seed], kind, distances, list(methods),
                  f"campus {seed}, {'street' if kind == 'road' else 'corridor'}")
    if len(ARGS.seed) > 1:
        for kind, distances in paths:
            table(records, kind, distances, list(methods),
                  f"campuses {', '.join(map(str, ARGS.seed))} together, {'street' if kind == 'road' else 'corridor'}")
    car = car_pairs()
    if car:
        for name, fn in methods.items():
            for k, (source, target, truth) in enumerate(car):
                records.append({"seed": None, "kind": "car", "distance": 45.0 * k, **run(name, fn, source, target, truth)})
        print("\nreal car pair (libpointmatcher), scan 401 in 400 turned by 0-315 deg: right / accepted right / "
              "confidently wrong of 8, confidence range, median ms")
        for name in methods:
            rs = [r for r in records if r["kind"] == "car" and r["method"] == name]
            c = [r["confidence"] for r in rs]
            right, accepted, wrong = counts(rs)
            print(f"{name:<22}{right:>4}/{accepted:>2}/{wrong:>2}   {min(c):.2f}-{max(c):.2f}"
                  f"{np.median([r['ms'] for r in rs]):>7.0f} ms")
    if ARGS.plot is not None:
        plot(ARGS.plot, [r for r in records if r["kind"] != "car"], ARGS.seed)
    if ARGS.out is not None:
        ARGS.out.mkdir(parents=True, exist_ok=True)
        path = ARGS.out / "results.json"
        path.write_text(json.dumps({"seeds": ARGS.seed, "load": load, "records": records}, indent=1))
        print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
