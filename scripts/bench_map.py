"""Localisation in a prebuilt map: `MapLocalizer` against Open3D FPFH + RANSAC + ICP, on held-out scans.

Maps are fused from held-out frames (each frame's points moved by its ground-truth pose into the world
frame, concatenated, voxelised): redkitchen validation frames 800-990 every 10th, each SUN3D fragment every
5th frame and, with --combined, the redkitchen and SUN3D-1 maps side by side 10 m apart (one map larger
than any scan: the candidate places do the work). Scans are the frames between map frames (an evenly
spread subset of --scans per map); off-map scans come from another building (SUN3D for redkitchen,
redkitchen for SUN3D, 7-Scenes stairs for the combined map). Per map and method: success (RE < 2 deg and
TE < 5 cm against T_map_scan = pose), confident-wrong (confidence >= 0.5 and not a success), off-map
acceptance (share of off-map scans with confidence >= 0.5) and median milliseconds per scan. The baseline
has no calibrated confidence: its "confidence" is the share of the scan (at the map's resolution) within
5 cm of the map after its pose, gated at the same 0.5. Its FPFH features of the map are computed per scan
(as `genreg_bench.baselines.fpfh_ransac_icp` does): its time includes them.

    python scripts/bench_map.py --scans 20 --threads 2
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scans", type=int, default=20, help="scans per map (evenly spread over the frames between)")
    p.add_argument("--off-map", type=int, default=10, help="off-map scans per map")
    p.add_argument("--stride", type=int, default=4, help="pixel stride of scans and map frames")
    p.add_argument("--voxel", type=float, default=0.02, help="map voxel, m")
    p.add_argument("--threads", type=int, default=2, help="torch and OpenMP threads")
    p.add_argument("--combined", action="store_true", help="also the redkitchen + SUN3D-1 map, 10 m apart")
    p.add_argument("--no-baseline", action="store_true", help="GenReg only")
    return p.parse_args()


ARGS = parse() if __name__ == "__main__" else None
if ARGS is not None:
    os.environ["OMP_NUM_THREADS"] = str(ARGS.threads)  # before Open3D loads

import numpy as np
import open3d as o3d
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from genreg_bench.baselines import BaselineParams, fpfh_ransac_icp
from genreg_core.data.rgbd import RGBDSequence
from genreg_core.geometry import apply_transform, make_transform
from genreg_core.localization import MapLocalizer
from genreg_core.metrics import transform_errors
from genreg_core.preprocess import voxel_downsample

GATE = 0.5  # confidence gate of "accepted"
FIT_DISTANCE = 0.05  # the baseline's fitness distance, m


@dataclass
class Scan:
    points: np.ndarray  # camera frame, m
    truth: np.ndarray | None  # T_map_scan, None: off the map


@dataclass
class MapCase:
    name: str
    map_xyz: np.ndarray
    scans: list[Scan] = field(default_factory=list)
    off_map: list[Scan] = field(default_factory=list)


def fused(seq: RGBDSequence, frames: list[int], stride: int, voxel: float, shift: np.ndarray | None = None) -> np.ndarray:
    world = np.concatenate([apply_transform(seq.pose(i), seq.points(i, stride=stride).astype(np.float64))
                            for i in frames])
    cloud = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world)).voxel_down_sample(voxel).points)
    return cloud if shift is None else cloud + shift


def spread(items: list[int], n: int) -> list[int]:
    """n items evenly spread over the list (all of them if n >= its length)."""
    if n >= len(items):
        return list(items)
    return [items[int(k)] for k in np.linspace(0, len(items) - 1, n).round()]


def cases(args: argparse.Namespace) -> list[MapCase]:
    kitchen, sun = RGBDSequence.redkitchen(), {f: RGBDSequence.sun3d(f) for f in (1, 2)}
    s = args.stride

    def scans(seq: RGBDSequence, frames: list[int], n: int, shift: np.ndarray | None = None) -> list[Scan]:
        move = np.eye(4) if shift is None else make_transform(np.eye(3), shift)
        return [Scan(seq.points(i, stride=s), move @ seq.pose(i)) for i in spread(frames, n)]

    def off(seq: RGBDSequence, frames: list[int], n: int) -> list[Scan]:
        return [Scan(seq.points(i, stride=s), None) for i in spread(frames, n)]

    k_map = list(range(800, 1000, 10))
    k_between = [i for i in range(800, 1000) if i not in k_map and i in kitchen]
    out = [MapCase("redkitchen 800-990/10", fused(kitchen, k_map, s, args.voxel), scans(kitchen, k_between, args.scans),
                   off(sun[1], list(sun[1].frame_indices), (args.off_map + 1) // 2)
                   + off(sun[2], list(sun[2].frame_indices), args.off_map // 2))]
    for f, seq in sun.items():
        frames = list(seq.frame_indices)
        on, between = frames[::5], [i for i in frames if i not in frames[::5]]
        out.append(MapCase(f"sun3d-{f} every 5th", fused(seq, on, s, args.voxel), scans(seq, between, args.scans),
                           off(kitchen, k_between, args.off_map)))
    if args.combined:
        shift = np.array([10.0, 0.0, 0.0])
        sun_frames = list(sun[1].frame_indices)
        both = np.concatenate([out[0].map_xyz, fused(sun[1], sun_frames[::5], s, args.voxel, shift)])
        stairs = [Scan(RGBDSequence.stairs(q).points(i, stride=s), None) for q in (1, 2, 3, 4)
                  for i in RGBDSequence.stairs(q).frame_indices]
        sun_between = [i for i in sun_frames if i not in sun_frames[::5]]
        out.append(MapCase("redkitchen + sun3d-1, 10 m apart", both,
                           scans(kitchen, k_between, (args.scans + 1) // 2)
                           + scans(sun[1], sun_between, args.scans // 2, shift),
                           spread_scans(stairs, args.off_map)))
    return out


def spread_scans(items: list[Scan], n: int) -> list[Scan]:
    return [items[k] for k in spread(list(range(len(items))), n)]


Method = Callable[[np.ndarray], tuple[np.ndarray, float]]  # scan -> (T_map_scan, confidence)


def genreg_method(case: MapCase) -> Method:
    loc = MapLocalizer(case.map_xyz)

    def run(scan: np.ndarray) -> tuple[np.ndarray, float]:
        r = loc.localize(scan)
        return r.transformation, r.confidence
    return run


def baseline_method(case: MapCase) -> Method:
    params = BaselineParams.metric_scene(threads=ARGS.threads if ARGS else 2)
    tree = cKDTree(case.map_xyz)

    def run(scan: np.ndarray) -> tuple[np.ndarray, float]:
        T, _ = fpfh_ransac_icp(scan, case.map_xyz, params)
        moved = apply_transform(T, voxel_downsample(scan, ARGS.voxel if ARGS else 0.02))
        return T, float(np.mean(tree.query(moved, k=1, distance_upper_bound=FIT_DISTANCE)[0] < FIT_DISTANCE))
    return run


def measure(case: MapCase, name: str, method: Method) -> dict[str, float]:
    ok = wrong = accepted = 0
    ms: list[float] = []
    for scan in tqdm(case.scans + case.off_map, desc=f"{case.name}: {name}", leave=False, file=sys.stderr):
        t0 = time.perf_counter()
        T, conf = method(scan.points)
        ms.append(1000 * (time.perf_counter() - t0))
        if scan.truth is None:
            accepted += conf >= GATE
            continue
        re, te = transform_errors(T, scan.truth)
        good = re < 2.0 and te < 0.05
        ok += good
        wrong += (not good) and conf >= GATE
    n = len(case.scans)
    return {"success": ok, "n": n, "confident_wrong": wrong, "off_accepted": accepted, "off_n": len(case.off_map),
            "ms": float(np.median(ms[:n])), "off_ms": float(np.median(ms[n:])) if len(ms) > n else float("nan")}


def main() -> int:
    args = ARGS or parse()
    torch.set_num_threads(args.threads)
    load = os.getloadavg()
    print(f"# Map localisation: {args.threads} threads (torch {torch.get_num_threads()}, OMP "
          f"{os.environ.get('OMP_NUM_THREADS')}), load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          f"{os.cpu_count()} cores; stride {args.stride}, map voxel {args.voxel} m; success: RE < 2 deg and "
          f"TE < 5 cm; accepted: confidence >= {GATE}")
    print("| map | map points | method | success | confident-wrong | off-map accepted | median ms (off-map) |")
    print("|---|---|---|---|---|---|---|")
    methods: dict[str, Callable[[MapCase], Method]] = {"GenReg MapLocalizer": genreg_method}
    if not args.no_baseline:
        methods["FPFH + RANSAC + ICP (fitness gate)"] = baseline_method
    for case in cases(args):
        for name, build in methods.items():
            r = measure(case, name, build(case))
            print(f"| {case.name} | {len(case.map_xyz)} | {name} | {r['success']}/{r['n']} | {r['confident_wrong']} | "
                  f"{r['off_accepted']}/{r['off_n']} | {r['ms']:.0f} ({r['off_ms']:.0f}) |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
