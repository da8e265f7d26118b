"""scripts/bench_lidar_map.py --quick: it runs, its table parses, and its placed share agrees with a truth the
test works out itself (the held-out poses drawn again from the world module, errors computed here, the truth
checked to put a scan onto the map)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from genreg_core.data import lidar_world as lw

REPO = Path(__file__).resolve().parent.parent
SCANS = 4


def rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def median_gap(points: np.ndarray, T: np.ndarray, tree: cKDTree) -> float:
    """Median distance (m) from the points moved by T (x' = R x + t) to the nearest map point."""
    return float(np.median(tree.query(points @ T[:3, :3].T + T[:3, 3], k=1)[0]))


def table_rows(report: str) -> dict[str, list[str]]:
    """Markdown table rows by their first cell."""
    rows = {}
    for line in report.splitlines():
        if line.startswith("| ") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells
    return rows


def test_quick_global_placed_share_matches_an_independent_truth(tmp_path):
    out = tmp_path / "run"
    done = subprocess.run(
        [sys.executable, "scripts/bench_lidar_map.py", "--quick", "--sections", "global,mirrored,tilted", "--scans",
         str(SCANS), "--indoor-scans", "0", "--mirrored-scans", "2", "--tilted-scans", "2", "--threads", "2",
         "--no-progress", "--out", str(out)],
        check=False, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = (out / "report.md").read_text()
    assert report.strip() in done.stdout
    assert re.search(r"load average at start \d+\.\d+", report) and "load average at end" in report
    row = table_rows(report)["roads"]
    n, placed_cell = int(row[1]), row[2]
    placed_reported = int(placed_cell.split("/")[0])
    assert n == SCANS and placed_cell.startswith(f"{placed_reported}/{SCANS}")
    for cell in row[5:8]:  # median, p95 and retrieval milliseconds
        assert float(cell) > 0

    results = json.loads((out / "results.json").read_text())
    meta = results["meta"]
    mirrored = [r for r in results["records"] if r["section"] == "mirrored"]  # no truth: counted by confidence
    row = table_rows(report)["2"]
    assert len(mirrored) == 2 and "truth" not in mirrored[0]
    assert row[1] == f"{sum(r['confidence'] >= meta['gate'] for r in mirrored)}/2"
    records = [r for r in results["records"] if r["section"] == "global" and r["kind"] == "roads"]
    assert len(records) == SCANS and not meta["train"] and meta["seed"] >= 7

    # the truth, drawn again: the world's held-out poses from the documented random stream
    world = lw.campus_world(meta["seed"], tuple(meta["blocks"]))
    truth = lw.test_poses(world, SCANS, np.random.default_rng([meta["seed"], meta["streams"]["roads"]]))
    tree = cKDTree(lw.cached_map(world))
    scan = lw.culled_scan(world.scene, truth[0], np.random.default_rng(0)).points.astype(np.float64)
    shifted = truth[0].copy()
    shifted[:3, 3] += [1.0, 1.0, 0.0]
    assert median_gap(scan, truth[0], tree) < 0.1  # the truth is T_map_scan: the scan lies on the map
    assert median_gap(scan, shifted, tree) > 0.3

    placed = []
    for rec, T in zip(records, truth):
        E = np.asarray(rec["estimate"])
        re_deg, te = rotation_deg(E[:3, :3].T @ T[:3, :3]), float(np.linalg.norm(E[:3, 3] - T[:3, 3]))
        assert np.allclose(rec["truth"], T)
        assert abs(te - rec["te_m"]) < 1e-6 and abs(re_deg - rec["re_deg"]) < 1e-3
        placed.append(re_deg < meta["max_re_deg"] and te < meta["max_te_m"])
        confident_wrong = rec["confidence"] >= meta["gate"] and not placed[-1]
        assert rec["confident_wrong"] == confident_wrong
    assert sum(placed) == placed_reported
    assert sum(placed) >= SCANS // 2, f"only {sum(placed)} of {SCANS} held-out scans placed on a one-block world"

    # the tilted section: a sensor 1.8 m above the base, 0.4 m forward, pitched down 20 deg, rolled 4 deg; its scans
    # judged against the sensor's pose in its own frame, against the base's (on the ground) once moved into it
    mount = np.eye(4)
    mount[:3, :3] = Rotation.from_euler("ZYX", [0.0, np.radians(20.0), np.radians(4.0)]).as_matrix()
    mount[:3, 3] = [0.4, 0.0, 1.8]
    bases = lw.test_poses(world, 2, np.random.default_rng([meta["seed"], meta["streams"]["tilted"]]), height=0.0)
    tilted = [r for r in results["records"] if r["section"] == "tilted"]
    kinds = list(dict.fromkeys(r["kind"] for r in tilted))
    assert len(tilted) == 6 and len(kinds) == 3 and "base_link" in kinds[2], kinds
    level = np.eye(4)
    level[:3, 3] = mount[:3, 3]
    truth_of = {kinds[0]: lambda base: base @ level, kinds[1]: lambda base: base @ mount, kinds[2]: lambda base: base}
    for rec in tilted:
        np.testing.assert_allclose(rec["truth"], truth_of[rec["kind"]](bases[rec["i"]]), atol=1e-9)
    sensor = bases[0] @ mount
    scan = lw.culled_scan(world.scene, sensor, np.random.default_rng(0)).points.astype(np.float64)
    assert median_gap(scan, sensor, tree) < 0.1  # the tilted sensor's scan lies on the map at its pose
    assert median_gap(scan @ mount[:3, :3].T + mount[:3, 3], bases[0], tree) < 0.1  # moved into the base: at the base's
    assert sum(r["placed"] for r in tilted if r["kind"] == kinds[2]) >= 1, tilted


def test_seated_tells_the_true_place_from_one_the_scan_does_not_fit(monkeypatch):
    """The look-alike diagnostic of the global section (`seated`: GICP from a pose against the whole map, its
    tracking confidence) seats a scan at its true pose and not at the same pose 30 m along the map's long side
    (a 1x1-block world with the shipped LiDAR profile; the truth from the world's own poses)."""
    monkeypatch.syspath_prepend(str(REPO / "scripts"))
    # imported, the script takes its default arguments, and sets these:
    monkeypatch.setenv("OMP_WAIT_POLICY", os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    monkeypatch.setenv("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "2"))  # restored after the test
    import bench_lidar_map as bench

    from genreg_core.localization import MapLocalizer
    from genreg_core.registration import Registrar

    world = lw.campus_world(bench.HELD_OUT_SEED, (1, 1))
    loc = MapLocalizer(lw.cached_map(world), registrar=Registrar.from_checkpoint(bench.SCENE_MODEL, bench.SCENE_REGISTRATION),
                       config=bench.lidar_config())
    truth = lw.test_poses(world, 1, np.random.default_rng([bench.HELD_OUT_SEED, 1]))[0]
    scan = lw.world_scan(world, truth, np.random.default_rng(0), bench.SCAN_SENSOR).points.astype(np.float64)
    far = truth.copy()
    far[:3, 3] += [30.0, 0.0, 0.0] if np.ptp(world.bounds[:2]) >= np.ptp(world.bounds[2:]) else [0.0, 30.0, 0.0]
    assert bench.seated(loc, scan, truth) >= bench.GATE > bench.seated(loc, scan, far)


def test_track_indoor_guesses_are_read_as_metres_and_degrees(monkeypatch):
    monkeypatch.syspath_prepend(str(REPO / "scripts"))
    monkeypatch.setenv("OMP_WAIT_POLICY", os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    monkeypatch.setenv("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "2"))
    import bench_lidar_map as bench

    assert bench.parse([]).indoor_guesses == ((0.3, 3.0), (1.0, 10.0))
    assert bench.parse(["--indoor-guesses", "0.5:5,2:10"]).indoor_guesses == ((0.5, 5.0), (2.0, 10.0))
    try:
        bench.parse(["--indoor-guesses", "2m"])
    except SystemExit as exc:
        assert exc.code == 2  # argparse's usage error
    else:
        raise AssertionError("a guess without its angle was taken")
