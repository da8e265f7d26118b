"""Build the campus LiDAR maps (`genreg_core.data.lidar_world.cached_map`) and measure worlds, scans and maps.

Per world size (--blocks): the area, primitives and survey poses; the seconds of one `world_scan` (the survey
sensor, VLP-32-like 32 x 1024 rays to 100 m, with 6 movers) at --scans held-out poses, and of the same scan by
`lidar_scan` of the whole scene (every ray against every primitive) at --full-scans of them; the map's points,
its points per square metre, the share outside the bounds and its build seconds (`cached_map`: built and
cached under --cache-dir unless already there, in which case the build seconds come from its .json).

    OMP_NUM_THREADS=1 python scripts/lidar_world_maps.py --blocks 1x1 2x1 2x2 4x3 --seed 0
"""

from __future__ import annotations

import argparse
import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core: the machine is shared
    os.environ.setdefault(_var, "1")

import json
import time

import numpy as np

from genreg_core.data import lidar_world as lw
from genreg_core.data.synthetic_lidar import lidar_scan


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--blocks", nargs="+", default=["1x1", "2x1", "2x2", "4x3"], help="world sizes, COLSxROWS")
    p.add_argument("--seed", type=int, default=0, help="world seed")
    p.add_argument("--spacing", type=float, default=3.0, help="survey pose spacing, m")
    p.add_argument("--voxel", type=float, default=0.1, help="map voxel, m")
    p.add_argument("--scans", type=int, default=20, help="held-out scans timed per world")
    p.add_argument("--full-scans", type=int, default=2, help="of them, also cast against the whole scene")
    p.add_argument("--cache-dir", default="cache/lidar_world", help="where maps are kept")
    return p.parse_args()


def main() -> None:
    a = parse()
    rows = []
    for text in a.blocks:
        blocks = tuple(int(v) for v in text.lower().split("x"))
        start = time.perf_counter()
        w = lw.campus_world(a.seed, blocks)  # type: ignore[arg-type]
        world_s = time.perf_counter() - start
        poses = lw.survey_poses(w, a.spacing)
        rng = np.random.default_rng(a.seed)
        held = lw.test_poses(w, a.scans, rng)
        times, full_times = [], []
        for k, T in enumerate(held):
            start = time.perf_counter()
            lw.world_scan(w, T, np.random.default_rng(k))
            times.append(time.perf_counter() - start)
            if k < a.full_scans:
                start = time.perf_counter()
                lidar_scan(w.scene, T, np.random.default_rng(k), lw.SURVEY_SENSOR)
                full_times.append(time.perf_counter() - start)
        path = lw.map_path(w, a.spacing, a.voxel, a.cache_dir)
        start = time.perf_counter()
        cloud = lw.cached_map(w, a.spacing, a.voxel, a.cache_dir)
        build_s = json.loads(path.with_suffix(".json").read_text())["build_seconds"] if path.with_suffix(
            ".json").exists() else time.perf_counter() - start
        xmin, xmax, ymin, ymax = w.bounds
        outside = ~((cloud[:, 0] >= xmin) & (cloud[:, 0] <= xmax) & (cloud[:, 1] >= ymin) & (cloud[:, 1] <= ymax))
        rows.append({
            "blocks": text, "area_m2": round(w.area_m2), "boxes": len(w.scene.box_yaw),
            "cylinders": len(w.scene.cylinders), "world_s": round(world_s, 3), "survey_poses": len(poses),
            "scan_s_mean": round(float(np.mean(times)), 3), "scan_s_p95": round(float(np.percentile(times, 95)), 3),
            "full_scene_scan_s": round(float(np.mean(full_times)), 2) if full_times else None,
            "map_points": len(cloud), "points_per_m2": round(len(cloud) / w.area_m2, 1),
            "outside_bounds": int(outside.sum()), "build_s": round(float(build_s), 1), "map": str(path),
        })
        print(json.dumps(rows[-1]), flush=True)
    keys = ["blocks", "area_m2", "boxes", "cylinders", "survey_poses", "scan_s_mean", "scan_s_p95",
            "full_scene_scan_s", "map_points", "points_per_m2", "outside_bounds", "build_s"]
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(str(r[k]) for k in keys) + " |")
    print(f"load average at the end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
