#!/usr/bin/env python3
"""Fit the confidence calibration of a shipped model on training pairs, or measure it on held-out ones.

    python scripts/calibrate_confidence.py fit 7scenes            # writes genreg_core/weights/7scenes.confidence.json
    python scripts/calibrate_confidence.py fit modelnet40_dgcnn
    python scripts/calibrate_confidence.py held-out 7scenes       # AUC, ECE, confident-wrong on held-out pairs
    python scripts/calibrate_confidence.py fit-tracking 7scenes   # adds MapLocalizer's tracking model
    python scripts/calibrate_confidence.py fit-map 7scenes        # adds MapLocalizer's model of global results
    python scripts/calibrate_confidence.py check-map 7scenes --pairs 8   # global localisation in training maps

`fit` registers training pairs through the public API with each refinement the calibration serves (the
current calibration, if any, choosing among PDSAC's modes as in use; fit twice after a change of features),
keeping every network pass's result (`RegistrationConfig.passes`: the objects' 4, seeds 0-3; scenes 1),
labels each result by the model's success rule, fits one logistic regression (scikit-learn) per refinement
over `genreg_core.confidence.FEATURES`
(the result's `verification`), prints their 5-fold cross-validated ROC AUC and expected calibration error
(ECE, 10 equal-width bins; a pair's passes in one fold), writes the calibration beside the checkpoint and a reliability diagram to
docs/reliability_<model>.png. `held-out` registers pairs never used for fitting with the shipped
calibration and prints the same figures per set, plus success and the confident-wrong count (confidence
>= 0.5 and wrong).

Training pairs (never the held-out ones):
- scene model `7scenes`, `config.SCENE_REGISTRATION` refined by GICP, point-to-plane ICP or not at all:
  redkitchen frames 0-799, frame pairs 1, 5, 10,
  30, 60, 90 and 300 frames apart (the last mostly without overlap), the source kidnapped (up to 45 deg
  about a random axis, 0.5 m). Success: RE < 2 deg and TE < 5 cm.
- object models, not refined, point-to-point or point-to-plane ICP:
  ModelNet40 train split (seen categories): clean pairs at N=512 up to 180 deg, and RPM-Net style
  partial-to-partial crops. Success: RE < 5 deg.
`fit-tracking` fits the model of `MapLocalizer`'s tracking results (`result.TRACKING_CALIBRATION`: GICP from a
guess against a map, no network pass) into the scene model's calibration, keeping its other models: maps
fused from every 10th redkitchen training frame of four 200-frame stretches (0-799), the frames between
as scans, each from guesses 2 cm / 1 deg to 1 m / 45 deg off the truth (scans of other stretches are not
used: their ground truth disagrees with the map's by up to 4 deg and 7 cm, 7-Scenes' drift). Its cross-validated figures and reliability diagram
(docs/reliability_7scenes_tracking.png) are printed and written as `fit`'s.
`fit-map` fits the model of `MapLocalizer`'s global results (`confidence.MAP_CALIBRATION`: a registration's
probability and the see-through share, `MapLocalizer.judged`) the same way: maps fused from every 10th frame
of redkitchen training stretches of 100 frames (starting at 0, 100, ..., 700) and 200 frames (0, 200, 400,
600); scans between the map frames, up to 70 frames before the stretch and 30-99 frames after it (never past
frame 799: partly off the map, where a pose slid along the room seats the scan as well as the right one), and
the scans between mirrored (x -> -x in the camera frame: a room laid out as the map's mirror image, as many
buildings' twin rooms are; every pose of them wrong). Every candidate result of a scan
(`MapLocalizer.searched`) is a row; a scan's rows share a fold (docs/reliability_7scenes_map.png).
`check-map` localises the same sets of scans in the 200-frame training maps as in use (`MapLocalizer.localize`,
no guess) and prints per set the scans placed (right at confidence >= 0.5), confidently wrong, and the median
time: the training-side check of a change to map localisation or its model; then again with each map beside
its mirror image 3 m away (twin rooms mapped apart: a map in two parts), where the mirrored scans are the
twin's, placed at the pose mirrored across.
Held-out pairs: redkitchen frames 800-999 (30, 60, 90 apart, kidnapped), SUN3D (unseen; 20 apart,
kidnapped); ModelNet40 test split, unseen categories (clean up to 180 deg; crops).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from genreg_bench.map_suite import GATE, MIRROR  # the map suite's gate and mirror (check-map, fit-map)
from genreg_bench.report import calibration_stats
from genreg_core.checkpoint import resolve_checkpoint
from genreg_core.confidence import ConfidenceModel, Logistic, calibration_path, feature_vector, file_sha256
from genreg_core.config import SCENE_MODEL, SCENE_REGISTRATION, RegistrationConfig
from genreg_core.data import FramePairs, ModelNetPairs, RGBDSequence, load_modelnet40
from genreg_core.data.modelnet40 import rpmnet_crop_pair
from genreg_core.errors import CheckpointError
from genreg_core.metrics import transform_errors
from genreg_core.registration import Registrar

REPO = Path(__file__).resolve().parent.parent
Pair = tuple[np.ndarray, np.ndarray, np.ndarray]  # source, target, T_target_source
SCENE_RULE = "RE < 2 deg and TE < 0.05 m"
OBJECT_RULE = "RE < 5 deg"


def kidnapped_frames(sequence: RGBDSequence, gaps: tuple[int, ...], frames: range | None, per_gap: int,
                     seed: int) -> dict[str, list[Pair]]:
    """`per_gap` evenly spread kidnapped frame pairs per gap."""
    sets = {}
    for gap in gaps:
        pairs = FramePairs(sequence, gap, frames, kidnap=True, seed=seed)
        picks = np.linspace(0, len(pairs) - 1, min(per_gap, len(pairs))).astype(int)
        sets[f"{sequence.name} {gap} apart"] = [(it["source"], it["target"], it["transform"].astype(np.float64))
                                                for it in (pairs[int(i)] for i in picks)]
    return sets


def object_pairs(split: str, categories: str, count: int, seed: int) -> dict[str, list[Pair]]:
    """`count` clean pairs (up to 180 deg) and `count` RPM-Net style crops of a ModelNet40 split."""
    shapes = load_modelnet40(split, categories)
    picks = np.linspace(0, len(shapes.points) - 1, count).astype(int)
    clean = ModelNetPairs(shapes, 512, "clean", max_angle_deg=180.0, seed=seed)
    crops = []
    for i in picks:
        source, target, T = rpmnet_crop_pair(shapes.points[i].astype(np.float64), np.random.default_rng((seed, 7, int(i))))
        crops.append((source.astype(np.float32), target.astype(np.float32), T))
    return {f"ModelNet40 {split} {categories} clean 180 deg": [
                (it["source"], it["target"], it["transform"].astype(np.float64)) for it in (clean[int(i)] for i in picks)],
            f"ModelNet40 {split} {categories} crops": crops}


def profiles(model: str) -> dict[str, RegistrationConfig]:
    """The refinements a model's calibration serves, each with the model's settings otherwise."""
    base = SCENE_REGISTRATION if model == SCENE_MODEL else RegistrationConfig()
    methods = ("gicp", "point_to_plane", "none") if model == SCENE_MODEL else ("none", "point_to_point", "point_to_plane")
    return {method: replace(base, refine=replace(base.refine, method=method)) for method in methods}


def success(model: str) -> tuple[str, Callable[[float, float], bool]]:
    if model == SCENE_MODEL:
        return SCENE_RULE, lambda re, te: re < 2.0 and te < 0.05
    return OBJECT_RULE, lambda re, te: re < 5.0


def training_sets(model: str, per_set: int) -> dict[str, list[Pair]]:
    if model == SCENE_MODEL:
        return kidnapped_frames(RGBDSequence.redkitchen(), (1, 5, 10, 30, 60, 90, 300), range(800), per_set, 2027)
    return object_pairs("train", "seen", per_set, 2027)


def held_out_sets(model: str, per_set: int) -> dict[str, list[Pair]]:
    if model == SCENE_MODEL:
        sets = kidnapped_frames(RGBDSequence.redkitchen(), (30, 60, 90), range(800, 1000), per_set, 2028)
        for fragment in (1, 2):
            sets.update(kidnapped_frames(RGBDSequence.sun3d(fragment), (20,), None, per_set // 2, 2028))
        return sets
    return object_pairs("test", "unseen", per_set, 2028)


def register(model: str, sets: dict[str, list[Pair]], calibrated: bool, candidates: bool = False
             ) -> Iterator[tuple[str, str, np.ndarray, float, bool, float, str]]:
    """(set, profile, features, confidence, success, ms, pair) of every pair under every profile of the model; with
    `candidates`, of every network pass's result (`RegistrationConfig.passes`, seeds 0, 1, ...): the calibration
    chooses among them, so it is fitted on them all."""
    _, ok = success(model)
    for profile, config in profiles(model).items():
        passes = config.passes if candidates else 1
        configs = [replace(config, seed=config.seed + j, passes=1) for j in range(passes)] if candidates else [config]
        loaded = Registrar.from_checkpoint(model, configs[0])
        calibration = loaded.calibration if calibrated else None
        regs = [Registrar(loaded.model, c, calibration) for c in configs]  # one model, loaded once
        for name, pairs in sets.items():
            for i, (source, target, T) in enumerate(tqdm(pairs, desc=f"{model} {profile} {name} ({passes} pass(es))",
                                                         leave=False)):
                for reg in regs:
                    t0 = time.perf_counter()
                    result = reg.register(source, target)
                    ms = 1e3 * (time.perf_counter() - t0)
                    re, te = transform_errors(result.transformation, T)
                    yield (name, profile, feature_vector(result.verification), result.confidence,
                           ok(re, te), ms, f"{name} {i}")


def summary(p: np.ndarray, y: np.ndarray) -> str:
    stats = calibration_stats(p, y)
    auc = "  –  " if stats["auc"] is None else f"{stats['auc']:.3f}"
    return (f"n {len(y):4d}  success {y.mean():6.1%}  AUC {auc}  ECE {stats['ece']:.3f}  "
            f"confident-wrong {stats['confident_wrong']} of {stats['confident']} at >= 0.5")


def reliability_diagram(p: np.ndarray, y: np.ndarray, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.calibration import calibration_curve

    observed, predicted = calibration_curve(y, p, n_bins=10, strategy="uniform")
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(5, 6), height_ratios=(3, 1), sharex=True)
    top.plot([0, 1], [0, 1], "k:", label="perfectly calibrated")
    top.plot(predicted, observed, "o-", label="GenReg")
    top.set_ylabel("observed success rate")
    top.set_title(title.replace(": ", ":\n", 1), fontsize=9)
    top.legend(loc="upper left")
    bottom.hist(p, bins=10, range=(0, 1))
    bottom.set_xlabel("confidence (predicted probability of success)")
    bottom.set_ylabel("results")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fitted_logistic(X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[Logistic, np.ndarray]:
    """A logistic regression (scikit-learn) of success on the features, and its 5-fold cross-validated
    probabilities of the same rows (the rows of one pair, its passes, in one fold)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import StratifiedGroupKFold, cross_val_predict

    regression = LogisticRegression(C=1.0, max_iter=5000)
    held = cross_val_predict(regression, X, y, groups=groups, method="predict_proba",
                             cv=StratifiedGroupKFold(5, shuffle=True, random_state=0))[:, 1]
    regression.fit(X, y)
    return Logistic(tuple(float(c) for c in regression.coef_[0]), float(regression.intercept_[0])), held


def save_calibration(model: str, fitted: dict[str, Logistic], description: str) -> Path:
    """Write the model's calibration with `fitted` (refinement -> model), keeping the shipped calibration's
    other models (`fit` and `fit-tracking` fit different ones) when it belongs to this checkpoint.
    `fitted_on` holds one "<models>: <training results>" part per fit."""
    checkpoint = resolve_checkpoint(model)
    try:
        shipped = ConfidenceModel.load(calibration_path(checkpoint), checkpoint)
    except CheckpointError:  # none yet, or another checkpoint's
        shipped = None
    kept = {} if shipped is None else {k: v for k, v in shipped.by_refinement.items() if k not in fitted}
    parts = [] if shipped is None else [part for part in shipped.fitted_on.split("; ")
                                         if set(part.split(": ")[0].split(", ")) <= set(kept)]
    calibration = ConfidenceModel({**kept, **fitted}, success(model)[0], file_sha256(checkpoint),
                                  "; ".join([*parts, f"{', '.join(fitted)}: {description}"]), time.strftime("%Y-%m-%d"))
    return calibration.save(calibration_path(checkpoint))


def fit(model: str, per_set: int) -> None:
    # the shipped calibration, if any, chooses among PDSAC's modes as it will in use; its features are refitted
    rows = list(register(model, training_sets(model, per_set), calibrated=True, candidates=True))
    rule, _ = success(model)
    fitted, held = {}, np.zeros(len(rows))
    print(f"{model}: {len(rows)} training results, one model per refinement, 5-fold cross-validated:")
    for method in profiles(model):
        mine = np.array([r[1] == method for r in rows])
        X = np.stack([r[2] for r, m in zip(rows, mine, strict=True) if m])
        y = np.array([r[4] for r, m in zip(rows, mine, strict=True) if m])
        groups = np.array([r[6] for r, m in zip(rows, mine, strict=True) if m])
        fitted[method], held[mine] = fitted_logistic(X, y, groups)
        print(f"  {method:16s} {'all':28s}", summary(held[mine], y))
        for name in dict.fromkeys(r[0] for r in rows):
            mask = mine & np.array([r[0] == name for r in rows])
            print(f"  {method:16s} {name:28s}", summary(held[mask], np.array([r[4] for r in rows])[mask]))
    y_all = np.array([r[4] for r in rows])
    sets = ", ".join(dict.fromkeys(r[0] for r in rows))
    print("wrote", save_calibration(model, fitted, f"{len(rows)} training results: {sets}"))
    figure = REPO / "docs" / f"reliability_{model}.png"
    reliability_diagram(held, y_all, f"{model}: training pairs, 5-fold cross-validated ({rule})", figure)
    print("wrote", figure)


def held_out(model: str, per_set: int) -> None:
    rows = list(register(model, held_out_sets(model, per_set), calibrated=True))
    p = np.array([r[3] for r in rows])
    y = np.array([r[4] for r in rows])
    rule, _ = success(model)
    print(f"{model}: held-out pairs, shipped calibration ({rule}); median {np.median([r[5] for r in rows]):.0f} ms")
    for profile in dict.fromkeys(r[1] for r in rows):
        for name in dict.fromkeys(r[0] for r in rows):
            mask = np.array([r[0] == name and r[1] == profile for r in rows])
            print(f"  {profile:22s} {name:30s}", summary(p[mask], y[mask]))
    print(f"  {'all':53s}", summary(p, y))
    reliability_diagram(p, y, f"{model}: held-out pairs ({rule})", REPO / "docs" / f"reliability_{model}_held_out.png")


TRACK_NOISE = ((0.02, 1.0), (0.05, 2.0), (0.1, 5.0), (0.2, 10.0), (0.4, 20.0), (1.0, 45.0))  # m, deg (std)


def tracking_rows(per_map: int, seed: int = 2027) -> Iterator[tuple[str, np.ndarray, bool]]:
    """(set, features, success) of tracking results on the redkitchen training maps (`fit-tracking`)."""
    from scipy.spatial.transform import Rotation

    from genreg_core.localization import MapLocalizer
    from genreg_core.preprocess import voxel_downsample

    kitchen, rng = RGBDSequence.redkitchen(), np.random.default_rng(seed)
    _, ok = success(SCENE_MODEL)
    for start in range(0, 800, 200):
        loc = MapLocalizer(kitchen.fused(range(start, start + 200, 10), stride=4))
        frames = [i for i in range(start, start + 200) if i % 10 and i in kitchen]
        for i in tqdm([frames[int(k)] for k in np.linspace(0, len(frames) - 1, min(per_map, len(frames)))],
                      desc=f"tracking {start}-{start + 199}", leave=False):
            scan, truth = voxel_downsample(kitchen.points(i, stride=4).astype(np.float64), loc.voxel_size), kitchen.pose(i)
            for sigma_t, sigma_r in TRACK_NOISE:
                guess = truth.copy()
                guess[:3, 3] += rng.normal(0.0, sigma_t, 3)
                guess[:3, :3] = Rotation.from_rotvec(np.deg2rad(sigma_r) * rng.normal(size=3)).as_matrix() @ guess[:3, :3]
                result = loc.track(scan, guess)
                errors = transform_errors(result.transformation, truth)
                yield f"{start}-{start + 199} {sigma_t} m", feature_vector(result.verification), ok(*errors)


def fit_tracking(model: str, per_map: int) -> None:
    from genreg_core.result import TRACKING_CALIBRATION

    if model != SCENE_MODEL:
        raise SystemExit(f"fit-tracking: map tracking is calibrated for the scene model {SCENE_MODEL}, not {model}")
    rows = list(tracking_rows(per_map))
    X, y = np.stack([r[1] for r in rows]), np.array([r[2] for r in rows])
    logistic, held = fitted_logistic(X, y, np.arange(len(y)))
    print(f"{model} {TRACKING_CALIBRATION}: {len(rows)} training results, 5-fold cross-validated:")
    print(f"  {'all':28s}", summary(held, y))
    for name in dict.fromkeys(r[0] for r in rows):
        mask = np.array([r[0] == name for r in rows])
        print(f"  {name:28s}", summary(held[mask], y[mask]))
    print("wrote", save_calibration(model, {TRACKING_CALIBRATION: logistic}, f"{len(rows)} tracking results on redkitchen 0-799 maps"))
    figure = REPO / "docs" / f"reliability_{model}_tracking.png"
    reliability_diagram(held, y, f"{model} map tracking: training maps, 5-fold cross-validated ({SCENE_RULE})", figure)
    print("wrote", figure)


# fit-map: training maps (every 10th frame of a stretch fused), as (frames in the stretch, its first frames): rooms
# partly mapped (100 frames) and as large as the held-out maps (200)
MAP_STRETCHES = ((100, range(0, 800, 100)), (200, range(0, 800, 200)))
MAP_BEYOND = (30, 100, 7)  # scans this many frames after the stretch's end: (first, stop, step)
MAP_BEFORE = (-70, 0, 7)  # ... and before its start


def map_sets(kitchen: RGBDSequence, start: int, length: int, per_map: int) -> dict[str, list[int]]:
    """The training scans of the map of frames start..start+length-1 (every 10th fused), by set: `per_map` of
    the frames between the map frames, the frames after the stretch (`MAP_BEYOND`) and before it
    (`MAP_BEFORE`), never outside 0-799, and the frames between again as "mirrored"."""
    between = [i for i in range(start, start + length) if i % 10]
    end = start + length
    sets = {"between": [between[int(k)] for k in np.linspace(0, len(between) - 1, per_map)],
            "beyond": list(range(end + MAP_BEYOND[0], end + MAP_BEYOND[1], MAP_BEYOND[2])),
            "before": list(range(start + MAP_BEFORE[0], start + MAP_BEFORE[1], MAP_BEFORE[2]))}
    sets["mirrored"] = sets["between"]  # no pose of a mirrored scan is right
    return {name: [i for i in frames if 0 <= i < 800 and i in kitchen] for name, frames in sets.items()}


def map_scan(kitchen: RGBDSequence, frame: int, name: str) -> np.ndarray:
    """A training frame's points (camera frame, every 4th pixel), mirrored (`MIRROR`) in the "mirrored" set."""
    return kitchen.points(frame, stride=4).astype(np.float64) * (MIRROR if name == "mirrored" else 1.0)


def map_rows(per_map: int) -> Iterator[tuple[str, int, np.ndarray, bool]]:
    """(set, scan, features, success) of every candidate of global results in the redkitchen training maps
    (`fit-map`)."""
    from genreg_core.confidence import MAP_FEATURES
    from genreg_core.localization import MapLocalizer
    from genreg_core.preprocess import voxel_downsample

    kitchen, scan_id = RGBDSequence.redkitchen(), 0
    _, ok = success(SCENE_MODEL)
    for length, start in [(length, start) for length, starts in MAP_STRETCHES for start in starts]:
        loc = MapLocalizer(kitchen.fused(range(start, start + length, 10), stride=4))
        for name, frames in map_sets(kitchen, start, length, per_map).items():
            for i in tqdm(frames, desc=f"map {start}+{length} {name}", leave=False):
                scan = voxel_downsample(map_scan(kitchen, i, name), loc.voxel_size)
                truth, scan_id = kitchen.pose(i), scan_id + 1
                for result in loc.searched(scan, loc.scan_geometry(scan)):
                    x = np.array([result.verification[f] for f in MAP_FEATURES])
                    yield name, scan_id, x, name != "mirrored" and ok(*transform_errors(result.transformation, truth))


TWIN_GAP = 3.0  # check-map's twin rooms: the mirror image this many metres beyond the map's +x side


def twin_rooms(room: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A map of twin rooms mapped apart: `room` and its mirror image across the plane `TWIN_GAP` / 2 beyond
    its largest x (x -> shift - x); and the 4x4 that maps a pose in the room of a scan mirrored in its camera
    frame (`MIRROR`) to its pose in the twin (T -> S M T M: a proper rigid motion)."""
    shift = 2.0 * float(room[:, 0].max()) + TWIN_GAP
    mirror = np.diag([*MIRROR, 1.0])
    to_twin = np.eye(4)
    to_twin[0, 3] = shift
    return np.concatenate([room, room * MIRROR + np.array([shift, 0.0, 0.0])]), to_twin @ mirror


def check_map(model: str, per_map: int) -> None:
    """`check-map`: scans of the 200-frame training maps localised as in use (`MapLocalizer.localize`, no
    guess): per set, placed (right at confidence >= 0.5), confident-wrong and the median time. Then the same
    maps as twin rooms (`twin_rooms`: two parts, `LocalizationConfig.part_gap`), the mirrored scans there
    being scans of the twin."""
    from genreg_core.localization import MapLocalizer

    if model != SCENE_MODEL:
        raise SystemExit(f"check-map: map localisation is calibrated for the scene model {SCENE_MODEL}, not {model}")
    kitchen, counts = RGBDSequence.redkitchen(), {}
    _, ok = success(SCENE_MODEL)
    length = 200
    for twins in (False, True):
        for start in dict(MAP_STRETCHES)[length]:
            room = kitchen.fused(range(start, start + length, 10), stride=4)
            fused, to_twin = twin_rooms(room) if twins else (room, None)
            loc = MapLocalizer(fused)
            for name, frames in map_sets(kitchen, start, length, per_map).items():
                key = f"{'twin rooms, ' if twins else ''}{name}"
                for i in tqdm(frames, desc=f"check {start}+{length} {key}", leave=False):
                    t0 = time.perf_counter()
                    result = loc.localize(map_scan(kitchen, i, name))
                    seconds = time.perf_counter() - t0
                    truth = kitchen.pose(i)
                    if to_twin is not None and name == "mirrored":
                        truth = to_twin @ truth @ np.diag([*MIRROR, 1.0])
                    right = (name != "mirrored" or twins) and ok(*transform_errors(result.transformation, truth))
                    confident = result.confidence >= GATE
                    counts.setdefault(key, []).append((confident and right, confident and not right, seconds))
    starts = ", ".join(map(str, dict(MAP_STRETCHES)[length]))
    print(f"{model} global localisation in the 200-frame training maps ({starts}), then as twin rooms "
          f"(mirrored scans: scans of the twin):")
    for name, rows in counts.items():
        placed, wrong, seconds = (np.array(column) for column in zip(*rows, strict=True))
        print(f"  {name:21s} placed {int(placed.sum())}/{len(rows)}  confident-wrong {int(wrong.sum())}  "
              f"median {1000 * np.median(seconds):.0f} ms")


def fit_map(model: str, per_map: int) -> None:
    from genreg_core.confidence import MAP_CALIBRATION

    if model != SCENE_MODEL:
        raise SystemExit(f"fit-map: map localisation is calibrated for the scene model {SCENE_MODEL}, not {model}")
    rows = list(map_rows(per_map))
    X, y, groups = np.stack([r[2] for r in rows]), np.array([r[3] for r in rows]), np.array([r[1] for r in rows])
    logistic, held = fitted_logistic(X, y, groups)
    print(f"{model} {MAP_CALIBRATION}: {len(rows)} candidate results of {len(set(groups))} training scans, "
          f"5-fold cross-validated (coef {np.round(logistic.coef, 3).tolist()}, intercept {logistic.intercept:.3f}):")
    print(f"  {'all':28s}", summary(held, y))
    for name in dict.fromkeys(r[0] for r in rows):
        mask = np.array([r[0] == name for r in rows])
        print(f"  {name:28s}", summary(held[mask], y[mask]))
    print("wrote", save_calibration(model, {MAP_CALIBRATION: logistic},
                                    f"{len(rows)} global results in redkitchen 0-799 maps, scans on and beyond them "
                                    "and mirrored"))
    figure = REPO / "docs" / f"reliability_{model}_map.png"
    reliability_diagram(held, y, f"{model} global results in maps: training maps, 5-fold cross-validated ({SCENE_RULE})",
                        figure)
    print("wrote", figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=("fit", "held-out", "fit-tracking", "fit-map", "check-map"))
    parser.add_argument("model", help="shipped model name (7scenes, modelnet40_dgcnn, modelnet40_partial, modelnet40)")
    parser.add_argument("--pairs", type=int, default=60, help="pairs per set, or scans per map set (default 60)")
    args = parser.parse_args(argv)
    modes = {"fit": fit, "held-out": held_out, "fit-tracking": fit_tracking, "fit-map": fit_map, "check-map": check_map}
    modes[args.mode](args.model, args.pairs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
