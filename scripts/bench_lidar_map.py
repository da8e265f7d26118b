"""LiDAR scans localised in large synthetic LiDAR maps (`genreg_core.data.lidar_world`) with the shipped LiDAR
map profile (`genreg_ros.config.LIDAR_MAP_OVERRIDES`: the place index retrieves 8 places and headings, the
map voxelised to 0.2 m on load; the scene model and registration profile).

    python scripts/bench_lidar_map.py --threads 2                     # held-out worlds, every section
    python scripts/bench_lidar_map.py --sections global,track --scans 20
    python scripts/bench_lidar_map.py --quick                         # a small world, few scans (< 2 min)
    python scripts/bench_lidar_map.py --train                         # the training worlds (seeds 0 and 1)

Worlds: `campus_world(seed, blocks)`. Seeds 0-2 are training worlds (settings may be chosen on them; --train
uses seed 0, and seed 1 for off-map scans); the default runs held-out worlds, seed 7 (--seed, 7 or more)
and seed + 1 for off-map scans, never used to choose a setting. Maps: `cached_map(world)` (the survey sensor
every 3 m along every road and corridor, fused at 0.1 m voxels; cache/lidar_world; --indoor-spacing: every so
many metres along the corridors instead, as a mapping robot walking them records far more often). Scans: one revolution of
a VLP-32-like sensor (32 beams, 1024 columns, 100 m) with 6 movers (cars, pedestrians) that the map does not
hold, at `test_poses` (0.6-2 m off the centre-lines, any heading; 1.8 m above the road, indoors at the floor
robot's height of `survey_poses`). A scan's truth is T_map_scan = T_world_sensor (maps are in the world
frame). Placed: RE < 2 deg and TE < 0.25 m; accepted: confidence >= 0.5; confident-wrong: accepted and not
placed. Random streams (numpy default_rng of [seed, stream]): road poses 1, indoor poses 2, their scans 3,
curve 10 + size, track 20, off-map 30, beyond 40, track-indoor 50, walk-indoor 60, tilted 70.

Sections (--sections, comma separated):
  global     the (4, 3)-block world's map: points (before and after the map voxel), area, places; road and
             indoor scans localised without a guess: placed, confident-wrong, time, the confidence of the
             wrong ones, whether the true place (within 3 m and 15 deg) was among the 8 retrieved, and how
             many of the scans not placed were put at a look-alike place (GICP from GenReg's pose seats the
             scan at a tracking confidence >= 0.5; `seated`)
  baselines  the first --baseline-scans road scans registered against the whole map by
             KISS-Matcher + point-to-plane and FPFH + RANSAC + ICP (`genreg_bench.baselines`) with
             `BaselineParams.metric_scene().scaled(10)`: the RGB-D settings x10 for LiDAR scale (0.5 m feature
             and KISS-Matcher voxels, 1 m normals, 2.5 m FPFH, 0.75 m RANSAC distance, 100k RANSAC iterations,
             ICP on 0.2 m voxels with a 0.5 m cut-off); the target is the map at GenReg's 0.2 m map voxel.
             They run in a worker process that holds the map; a scan that takes longer than
             --baseline-timeout seconds is stopped and counts as a failure at that time. Their time includes
             the map's features (computed per scan: they keep no map index); the map's load does not.
  curve      worlds of 1x1, 2x1, 2x2 and 4x3 blocks: area, map points, places, index build time, median
             localisation time and retrieval time (--curve-scans scans each); docs/lidar_map_curve.png
  build      a map of --build-points points (the 4x3 map, topped up with a random share of its points
             jittered by 2 cm): MapLocalizer construction, place index and GICP map (the model and the
             compiled kernels loaded before, as the node loads them at configure), first with an empty
             cache_dir, then 3 times from it (the median is the load time), each in a fresh process (peak
             resident memory: its VmHWM)
  track      10 Hz drives along the longest street (not the terraced one), 1 and 2 m between scans (10 and 20
             m/s), 1 m off its centre-line, an HDL-64-like sensor at 2048 columns (~100k points): the first
             scan localised without a guess, each next one as register_node starts it in map mode
             (`follow`), from the last accepted pose and from it moved on at the last two poses' velocity
             (`map.predict_motion`), judged as the node judges it (`follow`): scans not published, in state
             lost (no guess after 2 misses), published but not placed
  track-indoor the global section's corridor scans (--indoor-scans, its poses) localised from guesses off the
             truth by 0.3 m and 3 deg, and by 1 m and 10 deg (--indoor-guesses; each in a random direction and
             turn), each given as an operator's `initialpose` is (`localize(..., rough=True)`): placed,
             confident-wrong, TE, the largest error along the corridor of an accepted pose
  walk-indoor a 10 Hz walk at 1.5 m/s (0.15 m between scans, --walk-scans of them) along the main corridor,
             0.5 m right of its centre-line, at the indoor scans' height and sensor: the first scan from its
             true pose (as an operator's `initialpose` gives it), each next one as in track (both guesses);
             TE (and the published poses >= 0.1 m off), the error along the corridor, the poses named as well
             fitted along it (`flat_fit`)
  offmap     scans of another world (seed + 1) localised in the map: accepted count, time
  mirrored   the first --mirrored-scans road scans of the global section mirrored left to right in the
             sensor frame (y -> -y; z stays up): a twin street laid out as the map's mirror image, where no
             pose is right; accepted count, time
  beyond     the map of the survey poses west of the world's middle (x < 0); scans 2-30 m east of it
  tilted     road scans of a LiDAR mounted on a base (`TILTED_MOUNT`: 1.8 m up, 0.4 m forward, pitched down
             20 deg, rolled 4 deg) at --tilted-scans base poses: localised as they come (the sensor's frame,
             not z up) and moved into the base frame as register_node's `base_frame` / `base_T_source` move
             them (`NodeConfig.base_T_source_matrix`); beside them, a level sensor at the same height
  picture    docs/lidar_map_errors.png: the map from above (world x, y), the global section's scans coloured
             by TE

Threads: --threads for torch, OpenMP (OMP_NUM_THREADS) and small_gicp; OMP_WAIT_POLICY=PASSIVE unless set
(idle OpenMP workers that spin slow GICP several-fold when other processes share the cores). Tables
(markdown) go to stdout and runs/bench_lidar_map/<timestamp>/report.md, per-scan records to results.json
beside it; --quick writes its figures there too (not into docs/).
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import itertools
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Self

SECTIONS = ("global", "baselines", "curve", "build", "track", "track-indoor", "walk-indoor", "offmap", "mirrored",
            "beyond", "tilted", "picture")
QUICK_SECTIONS = ("global", "curve", "track", "offmap", "mirrored", "beyond", "picture")
HELD_OUT_SEED = 7  # the first held-out world seed
TRAINING_SEEDS = (0, 1, 2)


def blocks_arg(text: str) -> tuple[int, int]:
    nx, ny = (int(v) for v in text.lower().replace("x", ",").split(","))
    return nx, ny


INDOOR_GUESSES = ((0.3, 3.0), (1.0, 10.0))  # track-indoor: the guesses' offsets from the truth (m, deg)


def guesses_arg(text: str) -> tuple[tuple[float, float], ...]:
    """`m:deg,m:deg,...`: track-indoor's guesses, each off the truth by m metres and deg degrees."""
    return tuple((float(m), float(d)) for m, d in (pair.split(":") for pair in text.split(",")))


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=2, help="torch, Open3D, small_gicp and GICP threads")
    p.add_argument("--sections", default=None, help=f"comma-separated, of {','.join(SECTIONS)} (default: all; "
                                                    f"--quick: {','.join(QUICK_SECTIONS)})")
    p.add_argument("--quick", action="store_true", help="a 1x1-block world, few scans, no baselines or build")
    p.add_argument("--train", action="store_true", help="the training worlds (seed 0, off-map seed 1)")
    p.add_argument("--seed", type=int, default=None, help=f"world seed (default {HELD_OUT_SEED}; held out: >= 7)")
    p.add_argument("--blocks", type=blocks_arg, default=None, help="the main world's blocks (default 4,3)")
    p.add_argument("--scans", type=int, default=None, help="road scans of the global section (default 40)")
    p.add_argument("--indoor-scans", type=int, default=None, help="indoor scans of the global section (default 10)")
    p.add_argument("--baseline-scans", type=int, default=10, help="road scans the baselines register")
    p.add_argument("--baseline-timeout", type=float, default=180.0, help="a baseline's limit per scan, s")
    p.add_argument("--curve-scans", type=int, default=None, help="scans per world size (default 15)")
    p.add_argument("--curve-blocks", default=None, help="world sizes of the curve (default 1x1,2x1,2x2,4x3)")
    p.add_argument("--track-scans", type=int, default=None, help="scans of the drive (default 60)")
    p.add_argument("--walk-scans", type=int, default=None, help="scans of the corridor walk (default 200)")
    p.add_argument("--indoor-guesses", type=guesses_arg, default=INDOOR_GUESSES, help="track-indoor's guesses, "
                   "m:deg off the truth, comma-separated (default 0.3:3,1:10)")
    p.add_argument("--offmap-scans", type=int, default=None, help="off-map scans (default 20)")
    p.add_argument("--mirrored-scans", type=int, default=None, help="mirrored road scans (default 20)")
    p.add_argument("--beyond-scans", type=int, default=None, help="scans beyond the partial map (default 20)")
    p.add_argument("--tilted-scans", type=int, default=None, help="scans of the tilted section (default 20)")
    p.add_argument("--build-points", type=int, default=10_000_000, help="points of the build section's map")
    p.add_argument("--out", default=None, help="output folder (default runs/bench_lidar_map/<timestamp>)")
    p.add_argument("--figures", default=None, help="figure folder (default docs/; --quick: the output folder)")
    p.add_argument("--cache-dir", default="cache/lidar_world", help="where world maps are kept")
    p.add_argument("--indoor-spacing", type=float, default=None, help="m between the survey's scans in corridors "
                   "(default: every 3 m, as on roads)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--build-child", nargs=2, metavar=("MAP_NPY", "CACHE_DIR"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    quick = a.quick
    a.seed = a.seed if a.seed is not None else (0 if a.train else HELD_OUT_SEED)
    if a.train and a.seed not in TRAINING_SEEDS[:-1]:
        p.error(f"--train runs training worlds: --seed {TRAINING_SEEDS[0]} or {TRAINING_SEEDS[1]} (off-map: seed + 1)")
    if not a.train and a.seed < HELD_OUT_SEED and a.build_child is None:
        p.error(f"held-out worlds have seeds {HELD_OUT_SEED} and up (0-2 are training worlds: --train)")
    a.offmap_seed = a.seed + 1
    a.blocks = a.blocks or ((1, 1) if quick else (4, 3))
    defaults = {"scans": (6, 40), "indoor_scans": (2, 10), "curve_scans": (3, 15), "track_scans": (8, 60),
                "walk_scans": (20, 200), "offmap_scans": (3, 20), "mirrored_scans": (3, 20), "beyond_scans": (4, 20),
                "tilted_scans": (4, 20)}
    for name, (q, full) in defaults.items():
        if getattr(a, name) is None:
            setattr(a, name, q if quick else full)
    a.curve_blocks = [blocks_arg(b) for b in (a.curve_blocks or ("1x1" if quick else "1x1,2x1,2x2,4x3")).split(",")]
    a.sections = [s.strip() for s in (a.sections or ",".join(QUICK_SECTIONS if quick else SECTIONS)).split(",") if s.strip()]
    unknown = sorted(set(a.sections) - set(SECTIONS))
    if unknown:
        p.error(f"unknown sections {unknown}; known: {','.join(SECTIONS)}")
    return a


ARGS = parse() if __name__ == "__main__" else parse([])  # imported (a test, bench_lidar_node): the defaults
os.environ["OMP_NUM_THREADS"] = str(ARGS.threads)  # before Open3D and torch load
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # spinning OpenMP workers starve on a shared 2-core machine

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from genreg_core import kernels
from genreg_core.config import SCENE_MODEL, SCENE_REGISTRATION, LocalizationConfig
from genreg_core.data import lidar_world as lw
from genreg_core.data.synthetic_lidar import LidarSensor, sensor_pose
from genreg_core.geometry import apply_transform
from genreg_core.localization import MapLocalizer
from genreg_core.metrics import transform_errors
from genreg_core.preprocess import voxel_downsample
from genreg_core.registration import Registrar
from genreg_core.result import AS_WELL_FITTED, RegistrationResult
from genreg_ros.config import NodeConfig, profile_config
from genreg_ros.map_state import LOST, Localization, placement, scan_start
from genreg_ros.policy import judge
from genreg_ros.tracking import Tracker, motion_continues

GATE = 0.5  # accepted: confidence at least this
MAX_RE_DEG = 2.0  # placed: rotation error below this, deg
MAX_TE_M = 0.25  # placed: translation error below this, m
RETRIEVED_M = 3.0  # the true place was retrieved: a hit within this distance (xy) of the truth...
RETRIEVED_DEG = 15.0  # ...and this heading
SCAN_SENSOR = LidarSensor.vlp32(1024, max_range=100.0)  # the held-out scans' sensor
TRACK_SENSOR = LidarSensor.hdl64(2048, max_range=100.0)  # the drive's sensor (~100k points a revolution)
TRACK_OFFSET = 1.0  # the drive's lateral offset from the street's centre-line, m
TRACK_START = 20.0  # the drive starts this far along the street, m
BEYOND_BAND = (2.0, 30.0)  # beyond: scans this far east of the partial map's edge (the world's middle), m
BEYOND_BINS = ((2.0, 10.0), (10.0, 20.0), (20.0, 30.0))
WARM_LOADS = 3  # loads from the cache after the build (the median is the figure)
JITTER_M = 0.02  # build: the top-up points' jitter (normal, per axis), m
INDOOR_HEIGHT = float(inspect.signature(lw.survey_poses).parameters["indoor_height"].default)
MIRROR = np.array([1.0, -1.0, 1.0])  # the mirrored section's scans: y -> -y in the sensor frame
STREAMS = {"roads": 1, "indoor": 2, "scans": 3, "curve": 10, "track": 20, "offmap": 30, "beyond": 40,
           "track-indoor": 50, "walk-indoor": 60, "tilted": 70}
SCAN_PERIOD_NS = 100_000_000  # track, walk-indoor: a scan every 100 ms (10 Hz)
GUESSES = {False: "the last pose", True: "predicted (constant velocity)"}  # track, walk-indoor: map.predict_motion
FOLLOW_HEAD = ["step", "guess", "scans", "tracked ms median", "tracked ms p95", "TE median m", "TE max m",
               "RE max deg", "confidence median (min)", "not published", "in state lost", "published wrong"]
LIDAR_PROFILE = "genreg_lidar_map.yaml"  # the shipped params file whose settings every section runs with
WALK_STEP = 0.15  # walk-indoor: 1.5 m/s at 10 Hz, m between scans
WALK_OFFSET = 0.5  # walk-indoor: to the right of the main corridor's centre-line, m
BASELINES = ("kiss-matcher+p2plane", "fpfh+ransac+icp")
# tilted: the LiDAR's mounting on the base, [x, y, z, qx, qy, qz, qw] as register_node's base_T_source takes it
TILTED_MOUNT = (0.4, 0.0, 1.8, *Rotation.from_euler("ZYX", [0.0, np.radians(20.0), np.radians(4.0)]).as_quat())


# ----------------------------------------------------------------------------- helpers
def rng_of(stream: str, seed: int, extra: int = 0) -> np.random.Generator:
    """The random stream of a purpose (`STREAMS`) for a world seed."""
    return np.random.default_rng([seed, STREAMS[stream] + extra])


def lidar_node_config() -> NodeConfig:
    """The shipped LiDAR map profile's node settings (`config/genreg_lidar_map.yaml`)."""
    return profile_config(LIDAR_PROFILE)


def lidar_config() -> LocalizationConfig:
    """The shipped LiDAR map profile's localisation settings."""
    return lidar_node_config().map.localization


def pct(values: Iterable[float], q: float) -> float:
    v = np.asarray(list(values), dtype=np.float64)
    return float(np.percentile(v, q)) if len(v) else float("nan")


def fmt(value: float, digits: int = 0) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def code_state() -> str:
    """The commit the run imports and the files of the package that differ from it (uncommitted)."""
    def git(*cmd: str) -> str:
        done = subprocess.run(["git", *cmd], capture_output=True, text=True, check=False,
                              cwd=Path(__file__).resolve().parent.parent)
        return done.stdout.strip() if done.returncode == 0 else "?"

    dirty = git("diff", "--name-only", "HEAD", "--", "genreg_core", "genreg_ros", "genreg_bench").split()
    return f"commit {git('rev-parse', '--short', 'HEAD')}" + (f" with uncommitted changes to {', '.join(dirty)}"
                                                              if dirty else "")


def load_text() -> str:
    a, b, c = os.getloadavg()
    return f"{a:.2f} {b:.2f} {c:.2f}"


def progress(items: Iterable[Any], desc: str, total: int | None = None) -> Iterable[Any]:
    return tqdm(items, desc=desc, total=total, unit="scan", file=sys.stderr, disable=ARGS.no_progress, leave=False)


def placed(re_deg: float, te_m: float) -> bool:
    return bool(re_deg < MAX_RE_DEG and te_m < MAX_TE_M)


class Report:
    """Markdown lines printed as they come and written to report.md; per-scan records to results.json."""

    def __init__(self, out: Path, meta: dict[str, Any]) -> None:
        self.out, self.meta = out, meta
        self.lines: list[str] = []
        self.records: list[dict[str, Any]] = []
        out.mkdir(parents=True, exist_ok=True)

    def add(self, *lines: str) -> None:
        for line in lines:
            self.lines.append(line)
            print(line, flush=True)
        self.save()

    def table(self, head: list[str], rows: list[list[str]]) -> None:
        self.add("| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|",
                 *("| " + " | ".join(r) + " |" for r in rows), "")

    def save(self) -> None:
        (self.out / "report.md").write_text("\n".join(self.lines) + "\n")
        (self.out / "results.json").write_text(json.dumps({"meta": self.meta, "records": self.records}, indent=1))


@dataclasses.dataclass
class Setup:
    """A world, its map and a localiser built on it, with the build's timings."""

    world: lw.World
    map_xyz: np.ndarray
    loc: MapLocalizer
    timings: dict[str, float]


def build_setup(world: lw.World, map_xyz: np.ndarray, registrar: Registrar) -> Setup:
    """MapLocalizer on the map (profile settings), its place index and GICP map built now, each timed."""
    t0 = time.perf_counter()
    loc = MapLocalizer(map_xyz, registrar=registrar, config=lidar_config())
    t1 = time.perf_counter()
    loc.place_index()
    t2 = time.perf_counter()
    loc.whole_map()
    t3 = time.perf_counter()
    return Setup(world, map_xyz, loc, {"construct": t1 - t0, "index": t2 - t1, "whole_map": t3 - t2})


def retrieved_truth(loc: MapLocalizer, scan: np.ndarray, truth: np.ndarray) -> bool:
    """Whether the place index retrieves the true place (within `RETRIEVED_M` and `RETRIEVED_DEG`) among its
    `retrieve` hits for this scan (voxelised as `localize` does)."""
    hits = loc.place_index().retrieve(voxel_downsample(scan.astype(np.float64), loc.voxel_size), loc.config.retrieve)
    yaw = float(np.arctan2(truth[1, 0], truth[0, 0]))
    return any(np.linalg.norm(h.centre[:2] - truth[:2, 3]) < RETRIEVED_M and
               abs(np.degrees(np.angle(np.exp(1j * (h.yaw - yaw))))) < RETRIEVED_DEG for h in hits)


def seated(loc: MapLocalizer, scan: np.ndarray, T: np.ndarray) -> float:
    """How well the scan seats at (near) T_map_scan `T`: the tracking confidence of GICP from `T` against the
    whole map (`MapLocalizer.track`, the scan voxelised as `localize` does); 0 when the map holds too little."""
    tracked = loc.track(voxel_downsample(scan.astype(np.float64), loc.voxel_size), np.asarray(T, dtype=np.float64),
                        local=loc.whole_map())
    return 0.0 if tracked is None else float(tracked.confidence)


def localise(loc: MapLocalizer, scan: np.ndarray, truth: np.ndarray | None, section: str, kind: str, i: int,
             guess: np.ndarray | None = None, diagnose: bool = True, rough: bool = False
             ) -> tuple[dict[str, Any], RegistrationResult]:
    """One scan localised (timed) and its record: errors against `truth` (None: off the map); `rough`: the guess
    is an operator's `initialpose` (`MapLocalizer.localize`'s `rough`, as register_node passes it)."""
    t0 = time.perf_counter()
    result = loc.localize(scan, initial_guess=guess, rough=rough)
    seconds = time.perf_counter() - t0
    T = result.transformation
    rec: dict[str, Any] = {"section": section, "kind": kind, "i": i, "points": len(scan), "seconds": seconds,
                           "retrieve_s": result.timings.get("retrieve", float("nan")),
                           "confidence": float(result.confidence), "estimate": np.asarray(T).tolist(),
                           "unconstrained": list(result.unconstrained), "guess": guess is not None}
    if truth is not None:
        re, te = transform_errors(T, truth)
        rec.update(truth=np.asarray(truth).tolist(), re_deg=float(re), te_m=float(te), placed=placed(re, te))
        rec["confident_wrong"] = bool(rec["confidence"] >= GATE and not rec["placed"])
        if diagnose and guess is None and loc.config.retrieve:
            rec["truth_retrieved"] = retrieved_truth(loc, scan, truth)
            if not rec["placed"]:  # a look-alike place, or a miss? how well the scan seats at each pose
                rec["seated_truth"], rec["seated_estimate"] = seated(loc, scan, truth), seated(loc, scan, T)
    return rec, result


def pose_text(T: np.ndarray | list) -> str:
    T = np.asarray(T)
    return f"({T[0, 3]:.1f}, {T[1, 3]:.1f}) m, yaw {np.degrees(np.arctan2(T[1, 0], T[0, 0])):.0f} deg"


def summary_row(label: str, recs: list[dict[str, Any]]) -> list[str]:
    """| scans | n | placed | confident-wrong | truth retrieved | ms median | ms p95 | retrieval ms | wrong's conf |"""
    ok = [r["placed"] for r in recs]
    wrong = [r["confidence"] for r in recs if not r["placed"]]
    retrieved = [r["truth_retrieved"] for r in recs if "truth_retrieved" in r]
    ms = [1000 * r["seconds"] for r in recs]
    return [label, str(len(recs)), f"{sum(ok)}/{len(ok)} ({100 * np.mean(ok):.0f} %)" if ok else "-",
            str(sum(r["confident_wrong"] for r in recs)),
            f"{sum(retrieved)}/{len(retrieved)}" if retrieved else "-", fmt(pct(ms, 50)), fmt(pct(ms, 95)),
            fmt(pct([1000 * r["retrieve_s"] for r in recs], 50), 1),
            (f"{np.median(wrong):.2f} (max {max(wrong):.2f})" if wrong else "-")]


SUMMARY_HEAD = ["scans", "n", "placed", "confident-wrong", "true place retrieved", "ms median", "ms p95",
                "retrieval ms", "confidence of wrong ones: median (max)"]


def wrong_lines(recs: list[dict[str, Any]], label: str) -> list[str]:
    """One line per confident-wrong scan: its truth, where it was put, confidence, the rivals named."""
    out = []
    for r in recs:
        if r.get("confident_wrong"):
            out.append(f"- {label} scan {r['i']}: truth {pose_text(r['truth'])}, placed at {pose_text(r['estimate'])} "
                       f"(RE {r['re_deg']:.1f} deg, TE {r['te_m']:.2f} m), confidence {r['confidence']:.2f}; "
                       f"true place retrieved: {r.get('truth_retrieved', '-')}; "
                       f"unconstrained: {'; '.join(r['unconstrained']) or '-'}")
    return out


def lookalike_lines(recs: list[dict[str, Any]], label: str) -> list[str]:
    """Of the scans not placed, those put at a look-alike place: where the scan seats about as well as at its
    true one (GICP from GenReg's pose: tracking confidence >= `GATE`), which one scan cannot tell apart."""
    missed = [r for r in recs if "seated_estimate" in r]
    if not missed:
        return []
    alike = [r for r in missed if r["seated_estimate"] >= GATE]

    def span(values: list[float]) -> str:
        return f"{min(values):.2f}" + (f"-{max(values):.2f}" if max(values) > min(values) else "")

    text = (f"{label}: of {len(missed)} scans not placed, {len(alike)} put at a look-alike place (GICP from "
            f"GenReg's pose seats the scan at a tracking confidence >= {GATE}")
    if alike:
        text += (f": {span([r['seated_estimate'] for r in alike])} there, "
                 f"{span([r['seated_truth'] for r in alike])} at the truth")
    return [text + ")."]


def world_scans(world: lw.World, poses: np.ndarray, rng: np.random.Generator, desc: str,
                sensor: LidarSensor = SCAN_SENSOR) -> list[np.ndarray]:
    return [lw.world_scan(world, T, rng, sensor).points.astype(np.float64)
            for T in progress(poses, f"scans {desc}")]


# ----------------------------------------------------------------------------- sections
class Bench:
    def __init__(self, args: argparse.Namespace, report: Report, figures: Path) -> None:
        self.args, self.report, self.figures = args, report, figures
        self.registrar = Registrar.from_checkpoint(SCENE_MODEL, SCENE_REGISTRATION)
        self._main: Setup | None = None
        self.global_recs: list[dict[str, Any]] = []
        self.global_scans: list[np.ndarray] = []

    def world(self, seed: int, blocks: tuple[int, int]) -> lw.World:
        return lw.campus_world(seed, blocks)

    def map_of(self, world: lw.World) -> np.ndarray:
        return lw.cached_map(world, cache_dir=self.args.cache_dir, progress=not self.args.no_progress,
                             indoor_spacing=self.args.indoor_spacing)

    @property
    def main(self) -> Setup:
        if self._main is None:
            world = self.world(self.args.seed, self.args.blocks)
            self._main = build_setup(world, self.map_of(world), self.registrar)
        return self._main

    def road_scans(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """The global section's road poses and scans (the baselines take the first of them)."""
        s, a = self.main, self.args
        poses = lw.test_poses(s.world, a.scans, rng_of("roads", a.seed))
        if not self.global_scans:
            self.global_scans = world_scans(s.world, poses, rng_of("scans", a.seed), "roads")
        return poses, self.global_scans

    def run_global(self) -> None:
        s, a = self.main, self.args
        w, loc = s.world, s.loc
        self.report.add(f"## Global localisation: {w.key}", "",
                        f"Map: {len(s.map_xyz):,} points fused at 0.1 m ({len(loc.map):,} after the profile's "
                        f"{loc.config.map_voxel:g} m map voxel), {w.area_m2:,.0f} m^2 "
                        f"({w.bounds[1] - w.bounds[0]:.0f} x {w.bounds[3] - w.bounds[2]:.0f} m), "
                        f"{len(loc.place_index()):,} places; MapLocalizer construction {s.timings['construct']:.1f} s "
                        f"(model loaded before), place index {s.timings['index']:.1f} s, GICP map "
                        f"{s.timings['whole_map']:.1f} s. Scans: {SCAN_SENSOR.beams} beams x {SCAN_SENSOR.columns} "
                        f"columns, 6 movers. Load average {load_text()}.", "")
        poses, scans = self.road_scans()
        recs = [localise(loc, scan, T, "global", "roads", i)[0]
                for i, (T, scan) in enumerate(progress(list(zip(poses, scans)), "global roads"))]
        rows = [summary_row("roads", recs)]
        if a.indoor_scans and w.indoor:
            ipos = lw.test_poses(w, a.indoor_scans, rng_of("indoor", a.seed), height=INDOOR_HEIGHT, where="indoor")
            iscans = world_scans(w, ipos, rng_of("scans", a.seed, 1), "indoor")
            irecs = [localise(loc, scan, T, "global", "indoor", i)[0]
                     for i, (T, scan) in enumerate(progress(list(zip(ipos, iscans)), "global indoor"))]
            rows.append(summary_row(f"indoor ({INDOOR_HEIGHT:g} m high)", irecs))
            recs += irecs
        self.global_recs = recs
        self.report.records += recs
        self.report.table(SUMMARY_HEAD, rows)
        points = np.mean([r["points"] for r in recs])
        self.report.add(f"Scan points: {points:,.0f} (mean). Placed: RE < {MAX_RE_DEG:g} deg and TE < {MAX_TE_M:g} m; "
                        f"confident-wrong: confidence >= {GATE} and not placed. Load average {load_text()}.", "")
        self.report.add(*lookalike_lines([r for r in recs if r["kind"] == "roads"], "Roads"),
                        *lookalike_lines([r for r in recs if r["kind"] == "indoor"], "Corridors"), "")
        lines = wrong_lines(recs, "global")
        if lines:
            self.report.add("Confident-wrong scans:", *lines, "")

    def run_baselines(self) -> None:
        from genreg_bench.baselines import BaselineParams

        s, a = self.main, self.args
        k = min(a.baseline_scans, a.scans)
        poses, scans = self.road_scans()
        genreg = [r for r in self.global_recs if r["kind"] == "roads"][:k]
        if len(genreg) < k:
            genreg = [localise(s.loc, scans[i], poses[i], "baselines", "genreg", i)[0]
                      for i in progress(range(k), "GenReg", k)]
            self.report.records += genreg
        params = BaselineParams.metric_scene(a.threads).scaled(10.0)
        self.report.add(f"## Baselines on the first {k} road scans (whole map, {len(s.loc.map):,} points at 0.2 m)", "",
                        f"Settings: BaselineParams.metric_scene().scaled(10): KISS-Matcher voxel "
                        f"{params.kiss_voxel_size:g} m; FPFH on {params.feature_voxel_size:g} m voxels, normals "
                        f"{params.normal_radius:g} m, FPFH radius {params.fpfh_radius:g} m, RANSAC distance "
                        f"{params.ransac_distance:g} m, {params.ransac_max_iterations:,} iterations; ICP on "
                        f"{params.icp_voxel_size:g} m voxels, cut-off {params.refine_distance:g} m. Per-scan limit "
                        f"{a.baseline_timeout:g} s (stopped: a failure at that time). Load average {load_text()}.", "")
        rows = [self.baseline_row("GenReg MapLocalizer", genreg)]
        kiss_ms = float("nan")
        with BaselineWorker(s.map_xyz, s.loc.config.map_voxel, params, a.threads) as worker:
            for method in BASELINES:
                recs = []
                for i in progress(range(k), method, k):
                    T, seconds, error = worker.run(method, scans[i], a.baseline_timeout)
                    re, te = transform_errors(T, poses[i]) if T is not None else (float("inf"), float("inf"))
                    recs.append({"section": "baselines", "kind": method, "i": i, "seconds": seconds, "error": error,
                                 "re_deg": float(re), "te_m": float(te), "placed": placed(re, te),
                                 "estimate": None if T is None else T.tolist(), "truth": poses[i].tolist()})
                self.report.records += recs
                rows.append(self.baseline_row(method, recs))
                if method == "kiss-matcher+p2plane":
                    kiss_ms = pct([1000 * r["seconds"] for r in recs], 50)
        self.report.table(["method", "n", "placed", "ms median", "ms p95", "stopped / failed to run"], rows)
        g_ms = pct([1000 * r["seconds"] for r in genreg], 50)
        self.report.add(f"GenReg / KISS-Matcher median time on the same scans: {g_ms / kiss_ms:.3f} "
                        f"({g_ms:.0f} ms / {kiss_ms:.0f} ms). Load average {load_text()}.", "")

    @staticmethod
    def baseline_row(method: str, recs: list[dict[str, Any]]) -> list[str]:
        ok = [r["placed"] for r in recs]
        ms = [1000 * r["seconds"] for r in recs]
        errors = sum(1 for r in recs if r.get("error"))
        return [method, str(len(recs)), f"{sum(ok)}/{len(ok)} ({100 * np.mean(ok):.0f} %)", fmt(pct(ms, 50)),
                fmt(pct(ms, 95)), str(errors)]

    def run_curve(self) -> None:
        a = self.args
        self.report.add(f"## Time against map size ({a.curve_scans} road scans per world, seed {a.seed})", "")
        rows, points = [], []
        for n, blocks in enumerate(a.curve_blocks):
            if self._main is not None and blocks == a.blocks and a.seed == self._main.world.seed:
                s = self._main
            else:
                world = self.world(a.seed, blocks)
                s = build_setup(world, self.map_of(world), self.registrar)
            poses = lw.test_poses(s.world, a.curve_scans, rng_of("curve", a.seed, n))
            scans = world_scans(s.world, poses, rng_of("curve", a.seed, 100 + n), f"curve {blocks}")
            recs = [localise(s.loc, scan, T, "curve", f"{blocks[0]}x{blocks[1]}", i, diagnose=False)[0]
                    for i, (T, scan) in enumerate(progress(list(zip(poses, scans)), f"curve {blocks}"))]
            self.report.records += recs
            p = {"blocks": blocks, "area": s.world.area_m2, "points": len(s.map_xyz), "voxelised": len(s.loc.map),
                 "places": len(s.loc.place_index()), **s.timings,
                 "ms": pct([1000 * r["seconds"] for r in recs], 50), "ms95": pct([1000 * r["seconds"] for r in recs], 95),
                 "retrieve_ms": pct([1000 * r["retrieve_s"] for r in recs], 50),
                 "placed": sum(r["placed"] for r in recs), "n": len(recs)}
            points.append(p)
            rows.append([f"{blocks[0]}x{blocks[1]}", f"{p['area']:,.0f}", f"{p['points']:,}", f"{p['voxelised']:,}",
                         f"{p['places']:,}", f"{p['index']:.2f}", f"{p['whole_map']:.1f}", f"{p['placed']}/{p['n']}",
                         fmt(p["ms"]), fmt(p["ms95"]), fmt(p["retrieve_ms"], 1)])
            if s is not self._main:
                del s
        self.report.meta["curve"] = points
        self.report.table(["blocks", "area m^2", "map points", "after 0.2 m voxel", "places", "index build s",
                           "GICP map s", "placed", "ms median", "ms p95", "retrieval ms median"], rows)
        path = plot_curve(self.figures / "lidar_map_curve.png", points, a.seed)
        self.report.add(f"Figure: {path}. Load average {load_text()}.", "")

    def run_build(self) -> None:
        a = self.args
        world = self.world(a.seed, a.blocks)  # its map only: no localiser in this process while children run
        base = self.map_of(world)
        rng = np.random.default_rng([a.seed, 50])
        extra = max(0, a.build_points - len(base))
        with tempfile.TemporaryDirectory(prefix="bench_lidar_map_") as tmp:
            path = Path(tmp) / "map.npy"
            rows = rng.choice(len(base), extra, replace=extra > len(base)) if extra else np.zeros(0, np.int64)
            big = np.concatenate([base[: a.build_points], base[rows] + rng.normal(0.0, JITTER_M, (extra, 3)).astype(np.float32)])
            np.save(path, big)
            del big
            cache = Path(tmp) / "cache"
            runs = [build_child(path, cache, a.threads) for _ in range(1 + WARM_LOADS)]
        self.report.add(f"## Map build and load: {runs[0]['points']:,} points ({len(base):,} of the {world.key} map "
                        f"plus {extra:,} of them again, jittered by {JITTER_M * 100:g} cm), each run in a fresh process: "
                        f"built once, then loaded {WARM_LOADS} times", "")
        rows = []
        labels = ["built (empty cache_dir)", *(f"loaded (from cache_dir) {i + 1}" for i in range(WARM_LOADS))]
        for label, r in zip(labels, runs):
            rows.append([label, f"{r['load_npy']:.1f}", f"{r['model']:.1f}", f"{r['construct']:.1f}",
                         f"{r['index']:.1f}", f"{r['whole_map']:.1f}", f"{r['total']:.1f}", f"{r['maxrss_mb']:,.0f}",
                         f"{r['voxelised']:,}", f"{r['places']:,}"])
        self.report.meta["build"] = runs
        self.report.table(["run", "np.load s", "model + kernels load s", "MapLocalizer() s", "place index s", "GICP map s",
                           "total s (model + kernels excluded)", "peak RSS MB", "points after voxel", "places"], rows)
        c = lidar_config()
        loads = [r["total"] for r in runs[1:]]
        self.report.add(f"Load from cache: median {np.median(loads):.1f} s (of {', '.join(f'{t:.1f}' for t in loads)}), "
                        f"peak {max(r['maxrss_mb'] for r in runs[1:]):,.0f} MB. cache_dir holds the place index "
                        f"(places and their descriptors' spectra) and the map voxelised to {c.map_voxel:g} m, both "
                        "mapped from their files on load; the k-d tree and GICP's covariances are built on every load "
                        f"(on map_threads threads). Load average {load_text()}.", "")

    def run_track(self) -> None:
        a = self.args
        s = self.main
        w = s.world
        rows, steps = [], (1, 2)
        for step in steps:
            poses = drive_poses(w, a.track_scans * step)[::step]
            scans = world_scans(w, poses, rng_of("track", a.seed, step - 1), f"track {step} m", TRACK_SENSOR)
            for predict in (False, True):
                kind = f"{step} m, {'predicted' if predict else 'last pose'}"
                recs = follow(s.loc, poses, scans, "track", kind, None, predict)
                self.report.records += recs
                rows.append([f"{step} m ({10 * step} m/s)", GUESSES[predict], *follow_row(recs)])
        self.report.add(f"## Tracking: a 10 Hz drive, {a.track_scans} scans 1 or 2 m apart on {w.key}", "",
                        f"Along the longest street from {pose_text(drive_poses(w, 1)[0])}, {TRACK_OFFSET:g} m off its "
                        f"centre-line; {TRACK_SENSOR.beams} beams x {TRACK_SENSOR.columns} columns, about 100k "
                        "points per scan, 6 movers; the first scan without a guess, each next one as register_node "
                        "starts it in map mode (`follow`): a scan that moved beyond GICP's reach from its guess, "
                        f"or an unsure one, is searched by the place index. Load average {load_text()}.", "")
        self.report.table(FOLLOW_HEAD, rows)

    def run_track_indoor(self) -> None:
        a = self.args
        s = self.main
        w = s.world
        if not (a.indoor_scans and w.indoor):
            return
        poses = lw.test_poses(w, a.indoor_scans, rng_of("indoor", a.seed), height=INDOOR_HEIGHT, where="indoor")
        scans = world_scans(w, poses, rng_of("scans", a.seed, 1), "indoor")
        rng = rng_of("track-indoor", a.seed)
        rows = []
        for metres, degrees in a.indoor_guesses:
            recs = []
            for i, (T, scan) in enumerate(progress(list(zip(poses, scans)), f"track-indoor {metres:g} m")):
                heading = rng.uniform(-np.pi, np.pi)
                off = sensor_pose(metres * np.cos(heading), metres * np.sin(heading), 0.0,
                                  np.radians(degrees) * rng.choice([-1.0, 1.0]))
                rec, _ = localise(s.loc, scan, T, "track-indoor", f"{metres:g} m, {degrees:g} deg", i, T @ off,
                                  diagnose=False, rough=True)
                axis = corridor_axis(w, T)
                rec["along_m"] = abs(float((np.asarray(rec["estimate"])[:2, 3] - T[:2, 3]) @ axis))
                recs.append(rec)
            self.report.records += recs
            te = [r["te_m"] for r in recs]
            ms = [1000 * r["seconds"] for r in recs]
            wrong = [r for r in recs if r["confident_wrong"]]
            rows.append([f"{metres:g} m, {degrees:g} deg", str(len(recs)), f"{sum(r['placed'] for r in recs)}/{len(recs)}",
                         str(len(wrong)), fmt(pct(te, 50), 3),
                         fmt(max((r["along_m"] for r in recs if r["confidence"] >= GATE), default=float("nan")), 3),
                         ", ".join(f"{r['te_m']:.2f} m at {r['confidence']:.2f}" for r in wrong) or "-",
                         fmt(pct(ms, 50))])
        self.report.add(f"## Tracking in corridors: {len(poses)} corridor scans of {w.key} from a guess", "",
                        f"The global section's corridor scans ({INDOOR_HEIGHT:g} m high), each localised from its "
                        "truth moved by the offset in a random direction and turned by the angle either way, given "
                        "as an operator's `initialpose` is (searched `rough_reach` along a corridor). Load "
                        f"average {load_text()}.", "")
        self.report.table(["guess off by", "scans", "placed", "confident-wrong", "TE median m",
                           "largest error along the corridor, accepted m", "confident-wrong: TE at confidence", "ms median"], rows)
        clicks = [r for r in self.report.records if r["section"] == "track-indoor"]
        path = plot_clicks(self.figures / "lidar_initialpose.png", clicks, a.indoor_guesses, w.key)
        self.report.add(f"Figure: {path}.", "")

    def run_walk_indoor(self) -> None:
        a = self.args
        s = self.main
        w = s.world
        if not w.indoor:
            return
        poses = walk_poses(w, a.walk_scans)
        scans = world_scans(w, poses, rng_of("walk-indoor", a.seed), "walk")
        axis = corridor_axis(w, poses[0])
        rows = []
        for predict in (False, True):
            recs = follow(s.loc, poses, scans, "walk-indoor", "predicted" if predict else "last pose", poses[0],
                          predict)
            for r in recs:
                r["along_m"] = abs(float((np.asarray(r["estimate"])[:2, 3] - np.asarray(r["truth"])[:2, 3]) @ axis))
            self.report.records += recs
            published = [r for r in recs if r["published"]]
            named = sum(any(AS_WELL_FITTED in m for m in r["unconstrained"]) for r in published)
            rows.append([GUESSES[predict], *follow_row(recs), str(sum(r["te_m"] >= 0.1 for r in published)),
                         fmt(max((r["along_m"] for r in published), default=float("nan")), 3), str(named)])
        self.report.add(f"## Tracking in a corridor: a 10 Hz walk, {len(poses)} scans {WALK_STEP:g} m apart on {w.key}", "",
                        f"From {pose_text(poses[0])} to {pose_text(poses[-1])} along the main corridor, {WALK_OFFSET:g} m "
                        f"right of its centre-line, {INDOOR_HEIGHT:g} m high; {SCAN_SENSOR.beams} beams x "
                        f"{SCAN_SENSOR.columns} columns, 6 movers; the first scan from its true pose (as an "
                        "`initialpose`), each next one as register_node starts it in map mode (`follow`). Load "
                        f"average {load_text()}.", "")
        self.report.table(FOLLOW_HEAD[1:] + ["published >= 0.1 m off", "published: along the corridor max m",
                                             "published: named as well fitted"], rows)

    def run_offmap(self) -> None:
        a = self.args
        s = self.main
        other = self.world(a.offmap_seed, a.blocks)
        poses = lw.test_poses(other, a.offmap_scans, rng_of("offmap", a.offmap_seed))
        scans = world_scans(other, poses, rng_of("offmap", a.offmap_seed, 1), "off-map")
        recs = []
        for i, (T, scan) in enumerate(progress(list(zip(poses, scans)), "off-map")):
            rec, _ = localise(s.loc, scan, None, "offmap", other.key, i)
            rec["pose_in_other_world"] = T.tolist()
            rec["on_terrace"] = on_terrace(other, T)
            recs.append(rec)
        self.report.records += recs
        accepted = [r for r in recs if r["confidence"] >= GATE]
        placed_ms = [1000 * r["seconds"] for r in self.global_recs if r.get("placed")]
        self.report.add(f"## Off-map scans: {len(recs)} road scans of {other.key} localised in the {s.world.key} map",
                        "")
        conf = [r["confidence"] for r in recs]
        self.report.table(["scans", "accepted (confidence >= 0.5)", "confidence median (max)", "ms median", "ms p95",
                           "placed on-map scans' ms median (global)"],
                          [[str(len(recs)), f"{len(accepted)}/{len(recs)}", f"{np.median(conf):.2f} ({max(conf):.2f})",
                            fmt(pct([1000 * r["seconds"] for r in recs], 50)),
                            fmt(pct([1000 * r["seconds"] for r in recs], 95)), fmt(pct(placed_ms, 50))]])
        for r in accepted:
            self.report.add(f"- accepted off-map scan {r['i']}: taken at {pose_text(r['pose_in_other_world'])} in "
                            f"{other.key}{' (its terraced street)' if r['on_terrace'] else ''}, put at "
                            f"{pose_text(r['estimate'])}{' (the terraced street)' if on_terrace(s.world, r['estimate']) else ''}"
                            f", confidence {r['confidence']:.2f}")
        self.report.add(f"Load average {load_text()}.", "")

    def run_mirrored(self) -> None:
        a, s = self.args, self.main
        _, scans = self.road_scans()
        recs = []
        for i, scan in enumerate(progress(scans[: a.mirrored_scans], "mirrored")):
            rec, _ = localise(s.loc, scan * MIRROR, None, "mirrored", s.world.key, i)
            recs.append(rec)
        self.report.records += recs
        conf = [r["confidence"] for r in recs]
        ms = [1000 * r["seconds"] for r in recs]
        self.report.add(f"## Mirrored scans: {len(recs)} road scans of {s.world.key} mirrored left to right (y -> -y)", "")
        self.report.table(["scans", "accepted (confidence >= 0.5)", "confidence median (max)", "ms median", "ms p95"],
                          [[str(len(recs)), f"{sum(c >= GATE for c in conf)}/{len(recs)}",
                            f"{np.median(conf):.2f} ({max(conf):.2f})", fmt(pct(ms, 50)), fmt(pct(ms, 95))]])
        for r in recs:
            if r["confidence"] >= GATE:
                self.report.add(f"- accepted mirrored scan {r['i']}: put at {pose_text(r['estimate'])}, confidence "
                                f"{r['confidence']:.2f}; unconstrained: {'; '.join(r['unconstrained']) or '-'}")
        self.report.add(f"Load average {load_text()}.", "")

    def run_beyond(self) -> None:
        a = self.args
        w = self.main.world if self._main is not None else self.world(a.seed, a.blocks)
        edge = (w.bounds[0] + w.bounds[1]) / 2
        survey = lw.survey_poses(w)
        west = survey[survey[:, 0, 3] < edge]
        partial = partial_map(w, west, edge, Path(a.cache_dir))
        s = build_setup(w, partial, self.registrar)
        band = (edge + BEYOND_BAND[0], edge + BEYOND_BAND[1])
        strip = dataclasses.replace(w, roads=clip_lines(w.roads, *band), indoor=clip_lines(w.indoor, *band))
        poses = lw.test_poses(strip, a.beyond_scans, rng_of("beyond", a.seed))
        scans = world_scans(w, poses, rng_of("beyond", a.seed, 1), "beyond")
        recs = [localise(s.loc, scan, T, "beyond", "beyond", i)[0]
                for i, (T, scan) in enumerate(progress(list(zip(poses, scans)), "beyond"))]
        for r in recs:
            r["beyond_m"] = float(np.asarray(r["truth"])[0, 3] - edge)
        self.report.records += recs
        mapped_x = float(np.asarray(partial)[:, 0].max())
        self.report.add(f"## Beyond the map: the survey west of x = {edge:.0f} m ({len(west)} of {len(survey)} poses, "
                        f"{len(partial):,} points, reaching x = {mapped_x:.0f} m), scans {BEYOND_BAND[0]:g}-"
                        f"{BEYOND_BAND[1]:g} m east of x = {edge:.0f} m", "")
        rows = []
        for lo, hi in BEYOND_BINS:
            sub = [r for r in recs if lo <= r["beyond_m"] < hi]
            if sub:
                rows.append(summary_row(f"{lo:g}-{hi:g} m beyond", sub))
        rows.append(summary_row("all", recs))
        self.report.table(SUMMARY_HEAD, rows)
        lines = wrong_lines(recs, "beyond")
        self.report.add(*(["Confident-wrong scans:", *lines] if lines else []), f"Load average {load_text()}.", "")
        del s

    def run_tilted(self) -> None:
        a, s = self.args, self.main
        w = s.world
        mount = NodeConfig(base_frame="base_link", base_T_source=TILTED_MOUNT).base_T_source_matrix()
        level = np.eye(4)
        level[:3, 3] = mount[:3, 3]
        bases = lw.test_poses(w, a.tilted_scans, rng_of("tilted", a.seed), height=0.0)
        rows = []
        for label, T_base_sensor, into_base in (("level sensor, its frame", level, False),
                                                ("tilted sensor, its frame", mount, False),
                                                ("tilted sensor, moved into base_link", mount, True)):
            rng = rng_of("tilted", a.seed, 1)  # the same movers and noise for each sensor
            recs = []
            for i, T_base in enumerate(progress(bases, label)):
                scan = lw.world_scan(w, T_base @ T_base_sensor, rng, SCAN_SENSOR).points.astype(np.float64)
                if into_base:
                    scan, truth = apply_transform(T_base_sensor, scan), T_base
                else:
                    truth = T_base @ T_base_sensor
                recs.append(localise(s.loc, scan, truth, "tilted", label, i, diagnose=False)[0])
            self.report.records += recs
            rows.append(summary_row(label, recs))
        self.report.add(f"## A tilted LiDAR: {len(bases)} road poses of {w.key}", "",
                        f"The sensor ({SCAN_SENSOR.beams} beams) {mount[2, 3]:g} m above the base, {mount[0, 3]:g} m "
                        "forward, pitched down 20 deg and rolled 4 deg (`TILTED_MOUNT`), 6 movers; the same base "
                        "poses and random streams for each row. A scan localised in its own frame is judged against "
                        "the sensor's pose, one moved into the base frame (register_node's `base_frame`, "
                        "`base_T_source`) against the base's. Load average " + load_text() + ".", "")
        self.report.table(SUMMARY_HEAD, rows)

    def run_picture(self) -> None:
        if not self.global_recs:
            self.report.add("(picture: needs the global section)", "")
            return
        s = self.main
        path = plot_errors(self.figures / "lidar_map_errors.png", s.world, s.map_xyz, self.global_recs)
        self.report.add(f"Figure: {path} (colour: TE in cm, capped at 10; red crosses: not placed).", "")


# ----------------------------------------------------------------------------- geometry of the sections
def corridor_axis(world: lw.World, T: np.ndarray) -> np.ndarray:
    """The unit xy direction of the corridor centre-line segment nearest the pose T_world_sensor."""
    best, axis = np.inf, np.array([1.0, 0.0])
    for line in world.indoor:
        for a, b in itertools.pairwise(line):
            ab = b - a
            t = float(np.clip(np.dot(T[:2, 3] - a, ab) / np.dot(ab, ab), 0.0, 1.0))
            d = float(np.linalg.norm(T[:2, 3] - (a + t * ab)))
            if d < best:
                best, axis = d, ab / np.linalg.norm(ab)
    return axis


def drive_poses(world: lw.World, n: int) -> np.ndarray:
    """(n, 4, 4) T_world_sensor 1 m apart along the longest street off the terraced one, from `TRACK_START` m
    in, `TRACK_OFFSET` m to the right of its centre-line, heading along it, 1.8 m high."""
    def length(line: np.ndarray) -> float:
        return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())

    def terrace(line: np.ndarray) -> bool:
        return world.terrace is not None and lw.distance_to_lines(line.mean(0)[None], [world.terrace])[0] < 5.0

    line = max((r for r in world.roads if not terrace(r)), key=length)
    seg = np.diff(line, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    out = []
    for s in TRACK_START + np.arange(n, dtype=np.float64):
        s = min(s, cum[-1] - 1e-6)
        k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
        u = seg[k] / lengths[k]
        p = line[k] + u * (s - cum[k]) + np.array([u[1], -u[0]]) * TRACK_OFFSET
        c, sn = u
        T = np.eye(4)
        T[:2, :2] = [[c, -sn], [sn, c]]
        T[:3, 3] = [p[0], p[1], 1.8]
        out.append(T)
    return np.asarray(out)


def follow(loc: MapLocalizer, poses: np.ndarray, scans: list[np.ndarray], section: str, kind: str,
           first: np.ndarray | None, predict: bool) -> list[dict[str, Any]]:
    """Scans taken 100 ms apart localised one after another, each started and judged as register_node's map
    mode does (its `Tracker`, `map_state` and `policy.judge` with the LiDAR map profile's settings): the first from
    `first` (an `initialpose`; None: without a guess), each next one in state tracking from the last published
    pose, moved on at the velocity of the last two when `predict` (`map.predict_motion`; the scan after a pose
    placed by a search is then placed again, without a guess, and the two give the velocity); after
    `map.lost_after` misses in a row (state lost) from it too but searched for in the whole map as well, until
    a pose reaches `map.relocalize_confidence`. Each record has the state it
    was reported in and whether the node would publish it."""
    config = lidar_node_config()
    tracker, state, recs = Tracker(), Localization(config.map.lost_after), []
    if first is not None:
        tracker.set_guess(first, "map", None, "initialpose", -1.0)
    for i, (T, scan) in enumerate(progress(list(zip(poses, scans)), f"{section} {kind}")):
        stamp = i * SCAN_PERIOD_NS
        before = state.step()
        step, start = scan_start(before, tracker.start(config, "scan", "map", float(i), tracking=True,
                                                       parameter=False, stamp=stamp if predict else None),
                                 keep=config.map.localization.retrieve > 0)
        rec, result = localise(loc, scan, T, section, kind, i, start.T, diagnose=False, rough=start.rough)
        moved = placement(before, start, start.T is None or loc.within_reach(result.transformation, start.T, start.rough))
        publish = judge(result, config, relocalized=moved.relocalized).publish
        rec.update(state=state.update(step, publish), published=publish)
        recs.append(rec)
        if publish:
            tracker.record(result.transformation, stamp, tracker.generation, float(i),
                           continues=motion_continues(start.origin, moved.left), placed=moved.jumped)
    return recs


def follow_row(recs: list[dict[str, Any]]) -> list[str]:
    """`FOLLOW_HEAD`'s cells after the first two, of `follow`'s records (the first scan's time left out)."""
    tracked = recs[1:]
    ms, te = [1000 * r["seconds"] for r in tracked], [r["te_m"] for r in recs]
    return [str(len(recs)), fmt(pct(ms, 50)), fmt(pct(ms, 95)), fmt(pct(te, 50), 3), fmt(max(te), 3), fmt(max(r["re_deg"] for r in recs), 2),
            f"{np.median([r['confidence'] for r in tracked]):.2f} ({min(r['confidence'] for r in tracked):.2f})",
            str(sum(not r["published"] for r in recs)), str(sum(r["state"] == LOST for r in recs)),
            str(sum(r["published"] and not r["placed"] for r in recs))]


def walk_poses(world: lw.World, n: int) -> np.ndarray:
    """(n, 4, 4) T_world_sensor `WALK_STEP` m apart along the main corridor (`World.indoor[0]`) from its start (as
    far as it reaches), `WALK_OFFSET` m right of its centre-line, heading along it, at the indoor height."""
    a, b = world.indoor[0][0], world.indoor[0][-1]
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    out = []
    for s in np.minimum(np.arange(n) * WALK_STEP, length):
        T = np.eye(4)
        T[:2, :2] = [[u[0], -u[1]], [u[1], u[0]]]
        T[:2, 3] = a + u * s + np.array([u[1], -u[0]]) * WALK_OFFSET
        T[2, 3] = INDOOR_HEIGHT
        out.append(T)
    return np.asarray(out)


def on_terrace(world: lw.World, T: np.ndarray | list) -> bool:
    """Whether a pose lies on the world's terraced street (within 8 m of its centre-line)."""
    if world.terrace is None:
        return False
    return bool(lw.distance_to_lines(np.asarray(T)[None, :3, 3], [world.terrace])[0] < 8.0)


def clip_lines(lines: list[np.ndarray], x0: float, x1: float) -> list[np.ndarray]:
    """The parts of polylines with x0 <= x <= x1 (each straight piece clipped on its own)."""
    out = []
    for line in lines:
        for a, c in itertools.pairwise(line):
            dx = c[0] - a[0]
            if abs(dx) < 1e-9:
                if x0 <= a[0] <= x1:
                    out.append(np.stack([a, c]))
                continue
            f0, f1 = sorted(((x0 - a[0]) / dx, (x1 - a[0]) / dx))
            f0, f1 = max(f0, 0.0), min(f1, 1.0)
            if f1 - f0 > 1e-6 and np.linalg.norm(c - a) * (f1 - f0) > 1.0:
                out.append(np.stack([a + f0 * (c - a), a + f1 * (c - a)]))
    return out


def partial_map(world: lw.World, poses: np.ndarray, edge: float, cache_dir: Path) -> np.ndarray:
    """`build_map` of these survey poses (the survey sensor, voxel 0.1), kept beside `cached_map`'s maps."""
    full = lw.map_path(world, cache_dir=cache_dir)
    path = full.with_name(f"{full.stem}-west{edge:.0f}-{len(poses)}.npy")
    if path.exists():
        return np.load(path)
    cloud = lw.build_map(world, poses, progress=not ARGS.no_progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npy")
    np.save(tmp, cloud)
    os.replace(tmp, path)
    return cloud


# ----------------------------------------------------------------------------- figures
def plot_clicks(path: Path, recs: list[dict[str, Any]], guesses: Sequence[tuple[float, float]], key: str) -> Path:
    """track-indoor's clicks: per offset, the corridor scans accepted right and confidently wrong (left); every
    accepted pose's error (log scale) against its click's offset, the placed bound drawn (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    offsets = [m for m, _ in guesses]
    kinds = [f"{m:g} m, {d:g} deg" for m, d in guesses]
    by = [[r for r in recs if r["kind"] == k] for k in kinds]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.5))
    right_ = [sum(r["placed"] and r["confidence"] >= GATE for r in rs) for rs in by]
    wrong = [sum(r["confident_wrong"] for r in rs) for rs in by]
    x = np.arange(len(kinds))
    left.bar(x - 0.2, right_, 0.4, color="C2", label="accepted, right")
    left.bar(x + 0.2, wrong, 0.4, color="C3", label="accepted, wrong (confidence >= 0.5)")
    left.set(xticks=x, xticklabels=[f"{m:g} m\n{d:g} deg" for m, d in guesses], ylabel="corridor scans",
             xlabel="click off the truth", title=f"initialpose clicks in {key}'s corridors")
    left.legend(fontsize=8)
    for m, rs in zip(offsets, by, strict=True):
        accepted = [r for r in rs if r["confidence"] >= GATE]
        jitter = np.random.default_rng(0).uniform(-0.04, 0.04, len(accepted))
        right.scatter(m + jitter, [max(r["te_m"], 1e-3) for r in accepted], s=10,
                      c=["C3" if r["confident_wrong"] else "C2" for r in accepted])
    right.axhline(MAX_TE_M, color="0.4", ls=":", label=f"placed: TE < {MAX_TE_M:g} m")
    right.set(yscale="log", xlabel="click off the truth (m)", ylabel="accepted pose's translation error (m)",
              title="every accepted pose")
    right.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_curve(path: Path, points: list[dict[str, Any]], seed: int) -> Path:
    """Localisation time (median, p95 bar) and retrieval time against map area, log-log, with linear-growth
    references through the smallest map's point; index build time on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    area = np.array([p["area"] for p in points])
    ms, ms95 = np.array([p["ms"] for p in points]), np.array([p["ms95"] for p in points])
    ret = np.array([p["retrieve_ms"] for p in points])
    build = np.array([1000 * (p["index"] + p["whole_map"]) for p in points])
    order = np.argsort(area)
    i0 = order[0]
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.errorbar(area, ms, yerr=[np.zeros_like(ms), ms95 - ms], fmt="o-", color="C0", capsize=3,
                label="localisation without a guess (median, bar to p95)")
    ax.plot(area, ret, "s-", color="C1", label="place retrieval (median)")
    ax.plot(area, build, "^-", color="C2", label="place index + GICP map build (once per map)")
    span = np.array([area.min(), area.max()])
    for values, colour in ((ms, "C0"), (ret, "C1"), (build, "C2")):
        ax.plot(span, values[i0] * span / area[i0], ":", color=colour, alpha=0.7)
    ax.plot([], [], ":", color="0.4", label="linear growth from the smallest map")
    for p in points:
        ax.annotate(f"{p['blocks'][0]}x{p['blocks'][1]}", (p["area"], p["ms"]), textcoords="offset points",
                    xytext=(4, 6), fontsize=8)
    ax.set(xscale="log", yscale="log", xlabel="map area (m^2)", ylabel="time (ms)",
           title=f"GenReg LiDAR map localisation against map size (campus worlds, seed {seed})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_errors(path: Path, world: lw.World, map_xyz: np.ndarray, recs: list[dict[str, Any]]) -> Path:
    """The map from above in world x, y (at most `FIGURE_POINTS` of its points, grey) with the scans' true
    positions coloured by TE in cm (capped at 10, as `genreg_bench.map_suite.plot_map`), those not placed as red
    crosses, the terraced street and the corridors drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    from genreg_bench.map_suite import FIGURE_POINTS

    pts = map_xyz[np.random.default_rng(0).permutation(len(map_xyz))[:FIGURE_POINTS]]
    where = np.array([np.asarray(r["truth"])[:2, 3] for r in recs]).reshape(-1, 2)
    te = np.array([r["te_m"] for r in recs])
    ok = np.array([r["placed"] for r in recs], dtype=bool)
    indoor = np.array([r["kind"] == "indoor" for r in recs], dtype=bool)
    fig, ax = plt.subplots(figsize=(9, 7))
    ax.scatter(pts[:, 0], pts[:, 1], s=0.3, c="0.65", linewidths=0, rasterized=True)
    if world.terrace is not None:
        ax.plot(*np.asarray(world.terrace).T, "-", color="C1", lw=6, alpha=0.35,
                label=f"terraced street (repeats every {world.terrace_period:g} m)")
    for k, line in enumerate(world.indoor):
        ax.plot(*np.asarray(line).T, "-", color="C0", lw=4, alpha=0.35, label="corridors" if k == 0 else None)
    dots = ax.scatter(where[ok, 0], where[ok, 1], c=np.minimum(100 * te[ok], 10.0), cmap="viridis", vmin=0.0,
                      vmax=10.0, s=40, edgecolors="k", linewidths=0.5, label="placed")
    ax.scatter(where[~ok, 0], where[~ok, 1], c="red", marker="x", s=60, linewidths=2, label="not placed")
    cax = make_axes_locatable(ax).append_axes("right", size="3%", pad=0.1)
    fig.colorbar(dots, cax=cax, label="GenReg translation error (cm, capped at 10)")
    ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)",
           title=f"{world.key}: placed {int(ok[~indoor].sum())}/{int((~indoor).sum())} road and "
                 f"{int(ok[indoor].sum())}/{int(indoor.sum())} indoor scans (RE < {MAX_RE_DEG:g} deg, "
                 f"TE < {MAX_TE_M:g} m)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=4, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- processes
def build_child(map_path: Path, cache_dir: Path, threads: int) -> dict[str, Any]:
    """The build measured in a fresh process of this script (`--build-child`): its JSON line."""
    cmd = [sys.executable, __file__, "--threads", str(threads), "--no-progress", "--build-child", str(map_path),
           str(cache_dir)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB: VmHWM of /proc/self/status, the high-water mark of its own
    address space (ru_maxrss would carry over the forking parent's, kept across exec on Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def build_child_main(map_npy: str, cache_dir: str) -> int:
    """Load a map, build MapLocalizer (profile settings, `cache_dir`), its place index and GICP map; print the
    timings and the peak resident memory as one JSON line."""
    torch.set_num_threads(ARGS.threads)
    t0 = time.perf_counter()
    map_xyz = np.load(map_npy)
    t1 = time.perf_counter()
    registrar = Registrar.from_checkpoint(SCENE_MODEL, SCENE_REGISTRATION)
    kernels.compile_all()  # loaded before the map, as the node does at configure (numba's start: 0.2 s)
    t2 = time.perf_counter()
    loc = MapLocalizer(map_xyz, registrar=registrar, config=lidar_config(), cache_dir=cache_dir)
    t3 = time.perf_counter()
    places = len(loc.place_index())
    t4 = time.perf_counter()
    loc.whole_map()
    t5 = time.perf_counter()
    rss = peak_rss_mb()
    print(json.dumps({"points": len(map_xyz), "voxelised": len(loc.map), "places": places, "load_npy": t1 - t0,
                      "model": t2 - t1, "construct": t3 - t2, "index": t4 - t3, "whole_map": t5 - t4,
                      "total": (t5 - t0) - (t2 - t1), "maxrss_mb": rss}))
    return 0


def baseline_worker(conn: Connection, map_xyz: np.ndarray, voxel: float, params: Any, threads: int) -> None:
    """A process that holds the map (voxelised as GenReg's) and registers the scans it is sent."""
    torch.set_num_threads(threads)
    from genreg_bench.baselines import BASELINES as FUNCTIONS

    target = voxel_downsample(np.asarray(map_xyz, dtype=np.float64), voxel)
    conn.send("ready")
    while True:
        message = conn.recv()
        if message is None:
            return
        method, scan = message
        try:
            T, seconds = FUNCTIONS[method](scan, target, params)
            conn.send((np.asarray(T), seconds, ""))
        except Exception as exc:  # noqa: BLE001 (a baseline that raises has failed on this scan)
            conn.send((None, float("nan"), f"{type(exc).__name__}: {exc}"))


class BaselineWorker:
    """`baseline_worker` in a spawned process, restarted after a scan that ran past its time limit."""

    def __init__(self, map_xyz: np.ndarray, voxel: float, params: Any, threads: int) -> None:
        self.args = (map_xyz, voxel, params, threads)
        self.process: Any = None
        self.conn: Connection | None = None

    def start(self) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        self.process = ctx.Process(target=baseline_worker, args=(child, *self.args), daemon=True)
        self.process.start()
        child.close()
        self.conn = parent
        if parent.recv() != "ready":
            raise RuntimeError("the baseline worker did not start")

    def stop(self) -> None:
        if self.process is not None:
            if self.process.is_alive():
                self.process.terminate()
            self.process.join(10)
            self.process, self.conn = None, None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run(self, method: str, scan: np.ndarray, timeout: float) -> tuple[np.ndarray | None, float, str]:
        """(T or None, seconds, error text) of one registration; past `timeout` s the worker is stopped."""
        if self.process is None:
            self.start()
        assert self.conn is not None
        t0 = time.perf_counter()
        self.conn.send((method, scan))
        if self.conn.poll(timeout):
            try:
                return self.conn.recv()
            except EOFError:
                self.stop()
                return None, time.perf_counter() - t0, "worker died"
        self.stop()
        return None, timeout, "timeout"


# ----------------------------------------------------------------------------- main
def main() -> int:
    a = ARGS
    if a.build_child:
        return build_child_main(*a.build_child)
    torch.set_num_threads(a.threads)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = Path(a.out or f"runs/bench_lidar_map/{stamp}")
    figures = Path(a.figures) if a.figures else (out if a.quick else Path("docs"))
    meta: dict[str, Any] = {"argv": sys.argv[1:], "seed": a.seed, "offmap_seed": a.offmap_seed, "blocks": a.blocks,
                            "train": a.train, "quick": a.quick, "sections": a.sections, "indoor_spacing": a.indoor_spacing, "threads": a.threads,
                            "streams": STREAMS, "max_re_deg": MAX_RE_DEG, "max_te_m": MAX_TE_M, "gate": GATE,
                            "indoor_height": INDOOR_HEIGHT, "load_average_start": os.getloadavg(),
                            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "cores": os.cpu_count(),
                            "config": dataclasses.asdict(lidar_config()), "code": code_state()}
    report = Report(out, meta)
    report.add(f"# GenReg LiDAR map localisation ({'training' if a.train else 'held-out'} worlds: seed {a.seed}, "
               f"off-map seed {a.offmap_seed}; blocks {a.blocks[0]}x{a.blocks[1]})", "",
               f"Threads {a.threads} (torch {torch.get_num_threads()}, OMP_NUM_THREADS {os.environ['OMP_NUM_THREADS']}, "
               f"OMP_WAIT_POLICY {os.environ['OMP_WAIT_POLICY']}), "
               f"{os.cpu_count()} cores, load average at start {load_text()}; profile: "
               f"retrieve {lidar_config().retrieve}, map_voxel {lidar_config().map_voxel:g} m; map survey every 3 m "
               f"({'also in corridors' if a.indoor_spacing is None else f'every {a.indoor_spacing:g} m in corridors'}); sections "
               f"{','.join(a.sections)}; code: {code_state()}.", "")
    t0 = time.perf_counter()
    bench = Bench(a, report, figures)
    runs: dict[str, Callable[[], None]] = {
        "global": bench.run_global, "baselines": bench.run_baselines, "curve": bench.run_curve,
        "build": bench.run_build, "track": bench.run_track, "track-indoor": bench.run_track_indoor,
        "walk-indoor": bench.run_walk_indoor,
        "offmap": bench.run_offmap, "mirrored": bench.run_mirrored,
        "beyond": bench.run_beyond, "tilted": bench.run_tilted, "picture": bench.run_picture}
    for name in SECTIONS:
        if name in a.sections:
            start = time.perf_counter()
            runs[name]()
            report.meta.setdefault("section_seconds", {})[name] = time.perf_counter() - start
    meta.update(load_average_end=os.getloadavg(), wall_seconds=time.perf_counter() - t0)
    report.add(f"Wall time {meta['wall_seconds']:.0f} s; load average at end {load_text()}. Wrote {out / 'report.md'} "
               f"and {out / 'results.json'}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
