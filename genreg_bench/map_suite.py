"""Localisation in a prebuilt map (`genreg-bench --suite map`): `MapLocalizer` beside classical global
registration, on held-out scans.

Maps are fused from held-out frames (each frame's points moved by its ground-truth pose into the world
frame, concatenated, voxelised: `RGBDSequence.fused`; metres): redkitchen validation frames 800-990 every 10th, each SUN3D fragment
every 5th frame, a redkitchen map of frames 800-890 whose scans come from frames 930-999, partly beyond the
mapped stretch (where a pose slid along the room may seat a scan as well as the right one) and, with --combined-map, the redkitchen and SUN3D-1 maps side by side 10 m apart (one map
larger than any scan: the candidate places do the work). Scans are the frames between map frames (an evenly
spread subset per map); off-map scans come from another building (SUN3D for redkitchen, redkitchen for SUN3D,
7-Scenes stairs for the combined map); mirrored scans (--mirrored) are on-map scans of the map's own
sequence mirrored in their camera frame (x -> -x): a room laid out as the map's mirror image, as twin rooms
in many buildings are, where no pose is right unless the view is symmetric. A scan's truth is T_map_scan: it
maps the scan's camera-frame points into the map frame (the frame's pose, shifted with its map).

Methods, on the same scans:
- "GenReg MapLocalizer": `MapLocalizer.localize(scan)`, no guess;
- "GenReg MapLocalizer tracking": `localize(scan, initial_guess=...)` from the true pose of the frame
  `TRACK_LAG` frames earlier in the sequence (or the nearest earlier frame on disk); on-map scans only;
- "FPFH + RANSAC + ICP" and "KISS-Matcher + point-to-plane" (`genreg_bench.baselines`, metric-scene
  settings): no calibrated confidence, so theirs is a fitness gate: the share of the scan (voxelised at the
  map's resolution) within `FIT_DISTANCE` of the map after their pose. Their map features are computed per
  scan: their times include them.
Per map and method: success (RE < 2 deg and TE < 5 cm against the truth), confident-wrong (confidence >= 0.5
and not a success), off-map and mirrored acceptance (scans with confidence >= 0.5), median milliseconds
per scan (on-map, off-map) and, for MapLocalizer, the map's load time (its constructor, the model's
checkpoint included). Each confident result outside the rule is also measured against where small_gicp's GICP
started at the recorded pose settles on the map (`settled_truth`: the truth+gicp reference), listed under the
table: 7-Scenes' recorded poses disagree with their own depth by centimetres. Outputs in --out: report.md (the
table), results.json (per scan and method) and map_<key>.png (the map from above with the scans' true
positions coloured by GenReg's translation error).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from genreg_core.data.rgbd import REDKITCHEN_VAL_FRAMES, RGBDSequence
from genreg_core.geometry import apply_transform, make_transform
from genreg_core.metrics import transform_errors
from genreg_core.preprocess import voxel_downsample

GATE = 0.5  # confidence gate of "accepted"
MAX_RE_DEG = 2.0  # success: rotation error below this, degrees
MAX_TE = 0.05  # success: translation error below this, m
FIT_DISTANCE = 0.05  # the baselines' fitness distance, m
TRACK_LAG = 2  # tracking's guess: the true pose this many frames earlier
COMBINED_SHIFT = np.array([10.0, 0.0, 0.0])  # SUN3D-1 beside redkitchen in the combined map, m
BEYOND_MAP = range(800, 900, 10)  # the map of the scans beyond its stretch: redkitchen validation frames
BEYOND_SCANS = range(930, 1000)  # ... and the scans' frames: 3-10 s of camera motion past its last frame
MIRROR = np.array([-1.0, 1.0, 1.0])  # mirrored scans: x -> -x in the camera frame
FIGURE_POINTS = 50_000  # at most this many map points in a figure
METHODS = {  # --methods key -> table name
    "genreg": "GenReg MapLocalizer",
    "genreg-tracking": "GenReg MapLocalizer tracking",
    "fpfh+ransac+icp": "FPFH + RANSAC + ICP",
    "kiss-matcher+p2plane": "KISS-Matcher + point-to-plane",
}
TRACKING = "genreg-tracking"


@dataclass
class Scan:
    sequence: str  # RGBDSequence name
    frame: int
    points: np.ndarray  # (N, 3) camera frame, m
    truth: np.ndarray | None  # T_map_scan (4x4), None: off the map
    guess: np.ndarray | None = None  # tracking's T_map_scan: the truth TRACK_LAG frames earlier
    mirrored: bool = False  # the frame's points mirrored (`MIRROR`): no pose is right


@dataclass
class MapCase:
    key: str  # file-name part: map_<key>.png
    name: str
    map_xyz: np.ndarray  # (M, 3) map frame, m
    scans: list[Scan] = field(default_factory=list)
    off_map: list[Scan] = field(default_factory=list)  # off-map and mirrored scans (truth None)


def spread(items: list[Any], n: int) -> list[Any]:
    """n items evenly spread over the list (all of them if n >= its length)."""
    if n >= len(items):
        return list(items)
    return [items[int(k)] for k in np.linspace(0, len(items) - 1, n).round()]


def earlier_frame(frames: tuple[int, ...], frame: int, lag: int = TRACK_LAG) -> int | None:
    """The frame `lag` frames before `frame`, else the nearest earlier one on disk (None: none is earlier)."""
    earlier = [i for i in frames if i <= frame - lag] or [i for i in frames if i < frame]
    return max(earlier) if earlier else None


def on_map_scans(seq: RGBDSequence, frames: list[int], n: int, stride: int,
                 shift: np.ndarray | None = None) -> list[Scan]:
    """n scans spread over `frames`, each with T_map_scan = shift @ pose and its tracking guess."""
    move = np.eye(4) if shift is None else make_transform(np.eye(3), shift)

    def scan(i: int) -> Scan:
        before = earlier_frame(seq.frame_indices, i)
        guess = None if before is None else move @ seq.pose(before)
        return Scan(seq.name, i, seq.points(i, stride=stride), move @ seq.pose(i), guess)
    return [scan(i) for i in spread(frames, n)]


def off_map_scans(seqs: list[RGBDSequence], frames: list[list[int]], n: int, stride: int) -> list[Scan]:
    """n scans spread over the (sequence, frame) pairs, no truth."""
    pairs = [(seq, i) for seq, fs in zip(seqs, frames) for i in fs]
    return [Scan(seq.name, i, seq.points(i, stride=stride), None) for seq, i in spread(pairs, n)]


def mirrored_scans(scans: list[Scan], n: int) -> list[Scan]:
    """n of the on-map scans (evenly spread) mirrored in their camera frame (`MIRROR`), no truth."""
    return [Scan(s.sequence, s.frame, s.points * MIRROR.astype(s.points.dtype), None, mirrored=True)
            for s in spread(scans, n)]


def sequence_case(key: str, name: str, seq: RGBDSequence, map_frames: list[int], pool: list[int], n_scans: int,
                  off_map: list[Scan], stride: int, voxel: float, shift: np.ndarray | None = None) -> MapCase:
    """A map fused from `map_frames` and `n_scans` scans from the frames of `pool` between them."""
    on = set(map_frames)
    between = [i for i in pool if i in seq and i not in on]
    return MapCase(key, name, seq.fused(map_frames, stride, voxel) + (0.0 if shift is None else shift),
                   on_map_scans(seq, between, n_scans, stride, shift), off_map)


def map_cases(n_scans: int, n_off: int, stride: int, voxel: float, combined: bool = False,
              root: str | None = None) -> list[MapCase]:
    """The suite's maps: redkitchen, redkitchen beyond its stretch, SUN3D-1, SUN3D-2 (and, with `combined`, redkitchen + SUN3D-1)."""
    kitchen = RGBDSequence.redkitchen(root)
    sun = {f: RGBDSequence.sun3d(f, root) for f in (1, 2)}
    k_map, k_pool = list(REDKITCHEN_VAL_FRAMES)[::10], list(REDKITCHEN_VAL_FRAMES)
    k_between = [i for i in k_pool if i not in k_map and i in kitchen]
    sun_off = (off_map_scans([sun[1]], [list(sun[1].frame_indices)], (n_off + 1) // 2, stride)
               + off_map_scans([sun[2]], [list(sun[2].frame_indices)], n_off // 2, stride))
    out = [sequence_case("redkitchen", "redkitchen 800-990/10", kitchen, k_map, k_pool, n_scans, sun_off,
                         stride, voxel),
           sequence_case("beyond", "redkitchen 800-890/10, scans 930-999", kitchen, list(BEYOND_MAP), list(BEYOND_SCANS),
                         n_scans, [], stride, voxel)]
    for f, seq in sun.items():
        frames = list(seq.frame_indices)
        out.append(sequence_case(f"sun3d-{f}", f"sun3d-{f} every 5th", seq, frames[::5], frames, n_scans,
                                 off_map_scans([kitchen], [k_between], n_off, stride), stride, voxel))
    if combined:
        stairs = [RGBDSequence.stairs(q, root) for q in (1, 2, 3, 4)]
        k = sequence_case("redkitchen", "", kitchen, k_map, k_pool, (n_scans + 1) // 2, [], stride, voxel)
        frames = list(sun[1].frame_indices)
        s = sequence_case("sun3d-1", "", sun[1], frames[::5], frames, n_scans // 2, [], stride, voxel,
                          COMBINED_SHIFT)
        out.append(MapCase("combined", "redkitchen + sun3d-1, 10 m apart", np.concatenate([k.map_xyz, s.map_xyz]),
                           k.scans + s.scans,
                           off_map_scans(stairs, [list(q.frame_indices) for q in stairs], n_off, stride)))
    return out


Method = Callable[[Scan], tuple[np.ndarray, float]]  # scan -> (T_map_scan, confidence)


def genreg_methods(case: MapCase) -> tuple[dict[str, Method], float]:
    """MapLocalizer without and with a guess on one localiser, and its load time (constructor, s)."""
    from genreg_core.localization import MapLocalizer

    t0 = time.perf_counter()
    loc = MapLocalizer(case.map_xyz)
    load_s = time.perf_counter() - t0

    def run(scan: Scan) -> tuple[np.ndarray, float]:
        r = loc.localize(scan.points)
        return r.transformation, r.confidence

    def track(scan: Scan) -> tuple[np.ndarray, float]:
        r = loc.localize(scan.points, initial_guess=scan.guess)
        return r.transformation, r.confidence
    return {"genreg": run, TRACKING: track}, load_s


def baseline_methods(case: MapCase, threads: int, voxel: float) -> dict[str, Method]:
    """The classical pipelines, each with the fitness gate as its confidence."""
    from genreg_bench.baselines import BaselineParams, fpfh_ransac_icp, kiss_matcher_p2plane

    params = BaselineParams.metric_scene(threads=threads)
    tree = cKDTree(case.map_xyz)

    def gated(fn: Callable[..., tuple[np.ndarray, float]]) -> Method:
        def run(scan: Scan) -> tuple[np.ndarray, float]:
            T, _ = fn(scan.points, case.map_xyz, params)
            moved = apply_transform(T, voxel_downsample(scan.points, voxel))
            return T, float(np.mean(tree.query(moved, k=1, distance_upper_bound=FIT_DISTANCE)[0] < FIT_DISTANCE))
        return run
    return {"fpfh+ransac+icp": gated(fpfh_ransac_icp), "kiss-matcher+p2plane": gated(kiss_matcher_p2plane)}


def settled_truth(case: MapCase, threads: int) -> Callable[[Scan], np.ndarray]:
    """Where small_gicp's GICP started at a scan's recorded pose settles on the map (`baselines.truth_gicp`, the
    metric-scene settings; the "truth+gicp" reference of MODEL_CARD "The success rule against the recorded
    poses"): a reference for results outside the success rule, worked out once per scan."""
    from genreg_bench.baselines import BaselineParams, truth_gicp

    params, settled = BaselineParams.metric_scene(threads=threads), {}

    def settle(scan: Scan) -> np.ndarray:
        assert scan.truth is not None
        if (scan.sequence, scan.frame) not in settled:
            settled[scan.sequence, scan.frame] = truth_gicp(scan.points, case.map_xyz, params, scan.truth)[0]
        return settled[scan.sequence, scan.frame]
    return settle


def measure(case: MapCase, key: str, method: Method, progress: bool,
            settle: Callable[[Scan], np.ndarray] | None = None) -> list[dict[str, Any]]:
    """One record per scan: RE (deg), TE (m), success, confidence and milliseconds (tracking: on-map only). With
    `settle` (`settled_truth`), a confident result outside the rule also gets its errors against the settled
    truth (`settled_re_deg`, `settled_te_m`) and the recorded pose's distance from it (`truth_settled_te_m`)."""
    scans = case.scans if key == TRACKING else case.scans + case.off_map
    records = []
    for scan in tqdm(scans, desc=f"{case.name}: {METHODS[key]}", leave=False, file=sys.stderr, disable=not progress):
        t0 = time.perf_counter()
        T, conf = method(scan)
        rec: dict[str, Any] = {"map": case.key, "method": METHODS[key], "sequence": scan.sequence,
                               "frame": scan.frame, "on_map": scan.truth is not None, "mirrored": scan.mirrored,
                               "confidence": float(conf),
                               "ms": 1000 * (time.perf_counter() - t0), "re_deg": None, "te_m": None, "success": None}
        if scan.truth is not None:
            re, te = transform_errors(T, scan.truth)
            rec.update(re_deg=float(re), te_m=float(te), success=bool(re < MAX_RE_DEG and te < MAX_TE),
                       true_position_m=scan.truth[:3, 3].tolist())
            if settle is not None and conf >= GATE and not rec["success"]:
                settled = settle(scan)
                re_s, te_s = transform_errors(T, settled)
                rec.update(settled_re_deg=float(re_s), settled_te_m=float(te_s),
                           truth_settled_te_m=float(transform_errors(scan.truth, settled)[1]))
        records.append(rec)
    return records


def settled_line(case: MapCase, method: str, records: list[dict[str, Any]]) -> str | None:
    """A line on the confident results outside the rule (`measure` with `settle`): how many lie within the rule of
    the GICP-settled truth, and how far the recorded poses lie from it; None when there are none."""
    wrong = [r for r in records if "settled_te_m" in r]
    if not wrong:
        return None
    near = [r for r in wrong if r["settled_re_deg"] < MAX_RE_DEG and r["settled_te_m"] < MAX_TE]
    cm = [100 * r["settled_te_m"] for r in wrong]
    moved = [100 * r["truth_settled_te_m"] for r in wrong]
    return (f"- {case.name}, {method}: {len(wrong)} confident outside the rule; {len(near)} of them within it of "
            f"where GICP from the recorded pose settles (TE {min(cm):.1f}-{max(cm):.1f} cm from it; the recorded "
            f"poses lie {min(moved):.1f}-{max(moved):.1f} cm from it)")


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Success, confident-wrong, off-map and mirrored acceptance and median ms (on-map, off-map) of one map and
    method."""
    on = [r for r in records if r["on_map"]]
    off = [r for r in records if not r["on_map"] and not r.get("mirrored")]
    mirrored = [r for r in records if r.get("mirrored")]
    return {"success": sum(r["success"] for r in on), "n": len(on),
            "confident_wrong": sum(not r["success"] and r["confidence"] >= GATE for r in on),
            "off_accepted": sum(r["confidence"] >= GATE for r in off), "off_n": len(off),
            "mirrored_accepted": sum(r["confidence"] >= GATE for r in mirrored), "mirrored_n": len(mirrored),
            "ms": float(np.median([r["ms"] for r in on])) if on else float("nan"),
            "off_ms": float(np.median([r["ms"] for r in off])) if off else float("nan")}


TABLE_HEAD = ["| map | map points | map load s | method | success | confident-wrong | off-map accepted | mirrored "
              + "accepted | median ms (off-map) |", "|---|---|---|---|---|---|---|---|---|"]


def table_row(case: MapCase, method: str, load_s: float | None, s: dict[str, Any]) -> str:
    load = "-" if load_s is None else f"{load_s:.1f}"
    off = f"{s['off_accepted']}/{s['off_n']}" if s["off_n"] else "-"
    off_ms = f"{s['off_ms']:.0f}" if s["off_n"] else "-"
    mirrored = f"{s['mirrored_accepted']}/{s['mirrored_n']}" if s["mirrored_n"] else "-"
    return (f"| {case.name} | {len(case.map_xyz)} | {load} | {method} | {s['success']}/{s['n']} | "
            f"{s['confident_wrong']} | {off} | {mirrored} | {s['ms']:.0f} ({off_ms}) |")


def header(threads: int, stride: int, voxel: float) -> str:
    """The run's settings and machine state: threads, load average, cores."""
    load = os.getloadavg()
    return (f"# Map localisation: {threads} threads (torch {torch.get_num_threads()}, OMP "
            f"{os.environ.get('OMP_NUM_THREADS')}), load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
            f"{os.cpu_count()} cores; stride {stride}, map voxel {voxel} m; success: RE < {MAX_RE_DEG:g} deg and "
            f"TE < {100 * MAX_TE:g} cm; accepted: confidence >= {GATE}")


def plot_map(path: Path, title: str, map_xyz: np.ndarray, positions: np.ndarray, te_m: np.ndarray,
             success: np.ndarray) -> Path:
    """The map from above (its points on their two principal axes of largest variance, grey, at most
    `FIGURE_POINTS`) with the scans' true positions (K, 3) in metres, coloured by translation error in cm
    (capped at 10), failures as red crosses. Writes a PNG to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    rows = np.random.default_rng(0).permutation(len(map_xyz))[:FIGURE_POINTS]
    pts = map_xyz[rows]
    mean = pts.mean(axis=0)
    axes = np.linalg.svd(pts - mean, full_matrices=False)[2][:2].T  # (3, 2): largest-variance directions
    flat, where = (pts - mean) @ axes, (np.asarray(positions).reshape(-1, 3) - mean) @ axes
    ok = np.asarray(success, dtype=bool)
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.scatter(flat[:, 0], flat[:, 1], s=0.3, c="0.6", linewidths=0, rasterized=True)
    dots = ax.scatter(where[ok, 0], where[ok, 1], c=np.minimum(100 * np.asarray(te_m)[ok], 10.0), cmap="viridis",
                      vmin=0.0, vmax=10.0, s=40, edgecolors="k", linewidths=0.5, label="placed")
    ax.scatter(where[~ok, 0], where[~ok, 1], c="red", marker="x", s=60, linewidths=2, label="failed")
    cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.1)  # as tall as the map
    fig.colorbar(dots, cax=cax, label="GenReg translation error (cm, capped at 10)")
    ax.set(aspect="equal", xlabel="first principal axis (m)", ylabel="second principal axis (m)",
           title=f"{title}: GenReg placed {int(ok.sum())}/{len(ok)}")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_case(case: MapCase, records: list[dict[str, Any]], out: Path) -> Path:
    """`plot_map` of one map with GenReg's (no guess) on-map records, to out/map_<key>.png."""
    recs = [r for r in records if r["map"] == case.key and r["method"] == METHODS["genreg"] and r["on_map"]]
    return plot_map(out / f"map_{case.key}.png", case.name, case.map_xyz,
                    np.array([r["true_position_m"] for r in recs]), np.array([r["te_m"] for r in recs]),
                    np.array([r["success"] for r in recs], dtype=bool))


def settled_notes(notes: list[str]) -> list[str]:
    """The report's lines under the table on confident results outside the rule (`settled_line`)."""
    if not notes:
        return []
    head = ("Confident results outside the rule, against where small_gicp's GICP started at the recorded pose "
            "settles on the map (`baselines.truth_gicp`, the truth+gicp reference):")
    return ["", head, *notes]


def write_outputs(out: Path, lines: list[str], meta: dict[str, Any], records: list[dict[str, Any]]) -> None:
    """report.md (the table) and results.json (settings, per-scan records) into `out`."""
    (out / "report.md").write_text("\n".join(lines) + "\n")
    (out / "results.json").write_text(json.dumps({"meta": meta, "records": records}, indent=1))


def run_map_suite(args: argparse.Namespace) -> int:
    """`genreg-bench --suite map`: every map, every wanted method, table on stdout, files in --out."""
    wanted = args.methods or list(METHODS)
    unknown = sorted(set(wanted) - set(METHODS))
    if unknown:
        print(f"genreg-bench: unknown map methods {unknown}; known: {list(METHODS)}", file=sys.stderr)
        return 2
    stride = args.frame_stride or 4
    n_scans = 20 if args.pairs is None else args.pairs
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = [header(args.threads, stride, args.map_voxel), "", *TABLE_HEAD]
    print("\n".join(lines), flush=True)
    meta: dict[str, Any] = {"threads": args.threads, "load_average_start": os.getloadavg(), "cores": os.cpu_count(),
                            "stride": stride, "map_voxel_m": args.map_voxel, "scans": n_scans,
                            "off_map": args.off_map, "mirrored": args.mirrored, "gate": GATE,
                            "max_re_deg": MAX_RE_DEG, "max_te_m": MAX_TE,
                            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "maps": []}
    records: list[dict[str, Any]] = []
    notes: list[str] = []  # confident results outside the rule against the GICP-settled truth
    t0 = time.perf_counter()
    for case in map_cases(n_scans, args.off_map, stride, args.map_voxel, args.combined_map, args.data_root):
        if case.key != "beyond":  # that map checks scans past its stretch; the room maps check twins
            case.off_map += mirrored_scans(case.scans, args.mirrored)
        methods: dict[str, Method] = {}
        load_s = None
        if "genreg" in wanted or TRACKING in wanted:
            methods, load_s = genreg_methods(case)
        if set(wanted) - {"genreg", TRACKING}:  # the baselines' map tree only when they run
            methods.update(baseline_methods(case, args.threads, args.map_voxel))
        meta["maps"].append({"key": case.key, "name": case.name, "points": len(case.map_xyz), "load_s": load_s})
        settle = settled_truth(case, args.threads)
        for key in (k for k in METHODS if k in wanted):
            recs = measure(case, key, methods[key], not args.no_progress, settle)
            records += recs
            lines.append(table_row(case, METHODS[key], load_s if key in ("genreg", TRACKING) else None,
                                   summarize(recs)))
            print(lines[-1], flush=True)
            note = settled_line(case, METHODS[key], recs)
            if note:
                notes.append(note)
        if "genreg" in wanted:
            plot_case(case, records, out)
        meta.update(load_average_end=os.getloadavg(), wall_seconds=time.perf_counter() - t0)
        write_outputs(out, lines + settled_notes(notes), meta, records)
    if notes:
        print("\n".join(settled_notes(notes)))
    print(f"map suite: {meta['wall_seconds']:.0f} s with {args.threads} threads; wrote {out / 'report.md'}, "
          f"{out / 'results.json'}" + (f", {out}/map_*.png" if "genreg" in wanted else ""))
    return 0
