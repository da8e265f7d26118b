"""Loading a large map into `MapLocalizer`: seconds and peak memory, the first time and from the cache.

The map is the redkitchen validation map (frames 800-990, every 10th, pixel stride 2, 2 cm voxels) tiled
--points points large: copies 6 m apart on a 12-wide grid, each turned by a random yaw (a building of
kitchens). It is written once as a binary PLY in --workdir. Each load runs in its own process (its peak
resident memory, VmHWM, is its own): read the PLY (Open3D), `MapLocalizer(map, registrar=..., cache_dir=...)`,
then the candidate places for a redkitchen scan's radius (built, or read from the cache, which the first
load writes beside the map). The model is loaded before the clock starts (a node loads it once). Then a
scan of the first copy is tracked from a guess 5 cm and 3 deg off its true pose (milliseconds, errors).

    python scripts/bench_map_load.py --points 10000000 --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=10_000_000, help="map points")
    p.add_argument("--threads", type=int, default=2, help="torch, OpenMP, small_gicp and k-d tree threads")
    p.add_argument("--workdir", default="/tmp/genreg_map_load", help="where the map and its cache are written")
    p.add_argument("--child", choices=("load",), help=argparse.SUPPRESS)
    return p.parse_args(argv)


ARGS = parse() if __name__ == "__main__" else None
if ARGS is not None:
    os.environ["OMP_NUM_THREADS"] = str(ARGS.threads)  # before Open3D and torch load

import numpy as np
import open3d as o3d

from genreg_core.data.rgbd import RGBDSequence
from genreg_core.geometry import make_transform
from genreg_core.metrics import transform_errors

SCAN = 905  # a redkitchen validation frame between map frames


def build_map(path: Path, points: int) -> int:
    kitchen = RGBDSequence.redkitchen().fused(range(800, 1000, 10), stride=2)
    rng, tiles, total = np.random.default_rng(0), [], 0
    while total < points:
        k = len(tiles)
        yaw = 0.0 if k == 0 else rng.uniform(0.0, 2.0 * np.pi)
        rotation = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        tiles.append(kitchen @ rotation.T + [6.0 * (k % 12), 6.0 * (k // 12), 0.0])
        total += len(kitchen)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(tiles)[:points]))
    o3d.io.write_point_cloud(str(path), cloud, write_ascii=False)
    return len(tiles)


def peak_gb() -> float:
    line = next(x for x in Path("/proc/self/status").read_text().splitlines() if x.startswith("VmHWM"))
    return int(line.split()[1]) / 1e6


def child_load(args: argparse.Namespace) -> dict[str, float]:
    """One load in this process (the `--child` side)."""
    import torch

    from genreg_core.config import LocalizationConfig
    from genreg_core.localization import MapLocalizer
    from genreg_core.registration import Registrar

    torch.set_num_threads(args.threads)
    registrar = Registrar.from_checkpoint("7scenes")
    path, seq = Path(args.workdir) / "map.ply", RGBDSequence.redkitchen()
    t0 = time.perf_counter()
    points = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    t1 = time.perf_counter()
    loc = MapLocalizer(points, registrar=registrar, config=LocalizationConfig(voxel_size=0.02, threads=args.threads),
                       cache_dir=path.with_name(path.name + ".genreg-cache"))
    t2 = time.perf_counter()
    scan = seq.points(SCAN, stride=4)
    from genreg_core.preprocess import voxel_downsample

    _, radius, _ = loc.scan_geometry(voxel_downsample(scan.astype(np.float64), loc.voxel_size))
    places = loc.places(radius)
    t3 = time.perf_counter()
    truth = seq.pose(SCAN)
    off = make_transform(o3d.geometry.get_rotation_matrix_from_axis_angle(np.radians(3.0) * np.array([0.6, 0.0, 0.8])),
                         [0.03, -0.03, 0.02])
    ms = []
    for _ in range(5):  # the first builds the local map
        t = time.perf_counter()
        result = loc.localize(scan, initial_guess=off @ truth)
        ms.append(1e3 * (time.perf_counter() - t))
    re, te = transform_errors(result.transformation, truth)
    return {"read_s": t1 - t0, "localizer_s": t2 - t1, "places_s": t3 - t2, "total_s": t3 - t0, "places": len(places),
            "peak_gb": peak_gb(), "first_track_ms": ms[0], "track_ms": float(np.median(ms[1:])), "re": re, "te": te,
            "confidence": result.confidence}


def main() -> int:
    args = ARGS or parse()
    if args.child:
        print(json.dumps(child_load(args)))
        return 0
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    path = work / "map.ply"
    copies = build_map(path, args.points)
    for cached in (path.with_name(path.name + ".genreg-cache")).glob("*"):
        cached.unlink()
    load = os.getloadavg()
    print(f"# MapLocalizer map load: {args.points} points ({copies} kitchen copies, {path.stat().st_size / 1e6:.0f} MB "
          f"PLY), {args.threads} threads, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, {os.cpu_count()} cores")
    print("| load | read PLY s | MapLocalizer s | places s (count) | total s | peak RSS GB | tracking ms (first) | RE deg, TE cm, confidence |")
    print("|---|---|---|---|---|---|---|---|")
    for name in ("first (places built)", "again (places cached)"):
        out = subprocess.run([sys.executable, __file__, "--child", "load", "--threads", str(args.threads), "--workdir",
                              str(work)], capture_output=True, text=True, check=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        print(f"| {name} | {r['read_s']:.1f} | {r['localizer_s']:.1f} | {r['places_s']:.1f} ({r['places']}) | "
              f"{r['total_s']:.1f} | {r['peak_gb']:.2f} | {r['track_ms']:.0f} ({r['first_track_ms']:.0f}) | "
              f"{r['re']:.2f}, {100 * r['te']:.1f}, {r['confidence']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
