"""Map suite (`genreg-bench --suite map`): its ground truth puts held-out scans onto their map and off-map
scans nowhere on it (checked on the data, no registration), and its figure is written."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from genreg_bench.map_suite import (
    Scan,
    measure,
    mirrored_scans,
    off_map_scans,
    plot_map,
    sequence_case,
    settled_line,
    settled_truth,
    summarize,
)
from genreg_core.config import data_root
from genreg_core.data.rgbd import RGBDSequence

STRIDE = 8  # every 8th pixel: a quick map
ON_MAP_M = 0.02  # an on-map scan's median distance to the map stays below this, m
needs_data = pytest.mark.skipif(not ((data_root() / "7scenes").is_dir() and (data_root() / "sun3d").is_dir()),
                                reason="RGB-D data not available")


def median_gap(points: np.ndarray, T: np.ndarray, tree: cKDTree) -> float:
    """Median distance (m) from the points moved by T (x' = R x + t) to the nearest map point."""
    moved = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    return float(np.median(tree.query(moved, k=1)[0]))


@needs_data
def test_truth_puts_scans_on_the_map_and_off_map_scans_nowhere_on_it():
    kitchen, sun = RGBDSequence.redkitchen(), RGBDSequence.sun3d(1)
    map_frames = [800, 810, 820, 830]
    off = off_map_scans([sun], [list(sun.frame_indices)], 1, STRIDE)
    case = sequence_case("k", "kitchen", kitchen, map_frames, list(range(800, 830)), 3, off, STRIDE, 0.02)
    tree = cKDTree(case.map_xyz)
    assert len(case.scans) == 3 and len(case.off_map) == 1
    for scan in case.scans:
        assert scan.frame not in map_frames and scan.sequence == "redkitchen"
        assert np.array_equal(scan.points, kitchen.points(scan.frame, stride=STRIDE))
        assert median_gap(scan.points, scan.truth, tree) < ON_MAP_M, scan.frame
        assert np.allclose(scan.guess, kitchen.pose(scan.frame - 2))  # tracking starts 2 frames back
    scan = case.off_map[0]
    assert scan.truth is None and scan.sequence == "sun3d-1"
    assert np.array_equal(scan.points, sun.points(scan.frame, stride=STRIDE))
    # no camera pose of the map's sequence puts it on the map (a kitchen frame would lie on it at one of them)
    poses = [kitchen.pose(i) for i in range(800, 831)]
    assert min(median_gap(scan.points, T, tree) for T in poses) > 2 * ON_MAP_M


def test_plot_map_writes_a_png(tmp_path):
    rng = np.random.default_rng(0)
    map_xyz = rng.normal(size=(300, 3)) * [3.0, 1.5, 0.2]
    path = plot_map(tmp_path / "map_synthetic.png", "synthetic", map_xyz, map_xyz[:3], np.array([0.01, 0.2, 0.03]),
                    np.array([True, False, True]))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_mirrored_scans_are_the_scans_mirrored_and_counted_apart_from_off_map_ones():
    rng = np.random.default_rng(1)
    scans = [Scan("s", i, rng.normal(size=(50, 3)).astype(np.float32), np.eye(4)) for i in range(6)]
    mirrored = mirrored_scans(scans, 3)
    assert [m.frame for m in mirrored] == [0, 2, 5]  # evenly spread, ends included
    for m in mirrored:
        original = scans[m.frame].points
        assert m.truth is None and m.mirrored and m.points.dtype == original.dtype
        assert np.array_equal(m.points[:, 0], -original[:, 0]) and np.array_equal(m.points[:, 1:], original[:, 1:])
        # a reflection: no rotation maps the points onto their mirror image (determinant -1)
        assert np.linalg.det(np.linalg.lstsq(original, m.points, rcond=None)[0]) == pytest.approx(-1.0)
    records = ([{"on_map": True, "mirrored": False, "success": True, "confidence": 0.9, "ms": 50.0}]
               + [{"on_map": False, "mirrored": False, "confidence": c, "ms": 300.0} for c in (0.1, 0.6)]
               + [{"on_map": False, "mirrored": True, "confidence": c, "ms": 900.0} for c in (0.7, 0.8, 0.2)])
    s = summarize(records)
    assert (s["off_accepted"], s["off_n"], s["mirrored_accepted"], s["mirrored_n"]) == (1, 2, 2, 3)
    assert s["off_ms"] == 300.0  # mirrored scans are not in the off-map time


@needs_data
def test_a_confident_result_outside_the_rule_is_measured_against_the_settled_truth():
    """`measure` with `settled_truth`: a method that answers each scan's recorded pose moved 10 cm, at
    confidence 0.9, is confidently wrong; GICP started at the recorded pose settles within a few cm of it (the
    map is fused from the same sequence's poses), so the answer lies about 10 cm from the settled truth too, and
    the report's line counts none within the rule of it."""
    kitchen = RGBDSequence.redkitchen()
    case = sequence_case("k", "kitchen", kitchen, [800, 810, 820, 830], list(range(800, 830)), 2, [], STRIDE, 0.02)
    shift = np.array([0.1, 0.0, 0.0])

    def moved(scan: Scan) -> tuple[np.ndarray, float]:
        T = scan.truth.copy()
        T[:3, 3] += shift
        return T, 0.9

    records = measure(case, "genreg", moved, False, settled_truth(case, threads=2))
    assert len(records) == 2
    for rec in records:
        assert not rec["success"] and rec["te_m"] == pytest.approx(0.1)
        assert rec["truth_settled_te_m"] < 0.03
        assert rec["settled_te_m"] == pytest.approx(0.1, abs=rec["truth_settled_te_m"] + 1e-9)
    line = settled_line(case, "moved", records)
    assert line is not None and "2 confident outside the rule; 0 of them within it" in line
    assert settled_line(case, "moved", [{k: v for k, v in r.items() if not k.startswith("settled")}
                                        for r in records]) is None  # nothing confident outside the rule
