"""Benchmark harness: baselines recover a known transform, the smoke suite runs end to end on the shipped
models (`modelnet40`, `7scenes`) and registers its pairs to their known truth, report math."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from genreg_bench import report
from genreg_bench.baselines import BASELINES, BaselineParams, truth_gicp
from genreg_bench.datasets import (
    DATASETS,
    SCENE_ONLY_METHODS,
    BenchOptions,
    PairTruth,
    Suite,
    pair_truth,
    select_indices,
)
from genreg_bench.runner import run_benchmark
from genreg_core.errors import DataNotFoundError
from genreg_core.metrics import transform_errors

REPO = Path(__file__).resolve().parent.parent


def _bumpy_surface(n: int, rng: np.random.Generator) -> np.ndarray:
    """An asymmetric height field in the unit box: curvature everywhere, so FPFH and ICP lock on."""
    x, y = rng.random(n), rng.random(n)
    z = (0.25 * np.sin(3 * x) * np.cos(2 * y) + 0.3 * np.exp(-((x - 0.3) ** 2 + (y - 0.7) ** 2) / 0.02)
         - 0.2 * np.exp(-((x - 0.75) ** 2 + (y - 0.25) ** 2) / 0.03) + 0.3)
    return np.column_stack([x, y, z])


# Unit-box baselines; the scene-only accurate RANSAC and KISS-Matcher (built for scans) are tested on a scene pair.
@pytest.mark.parametrize("name", sorted(set(BASELINES) - {"fpfh+ransac+icp-accurate", "kiss-matcher+p2plane"}))
def test_baseline_recovers_a_known_transform(name):
    rng = np.random.default_rng(0)
    source = _bumpy_surface(1000, rng)
    T = np.eye(4)  # independent truth: scipy rotation, hand-picked translation
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(15.0) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)).as_matrix()
    T[:3, 3] = [0.05, -0.03, 0.02]
    target = (source @ T[:3, :3].T + T[:3, 3])[rng.permutation(len(source))]  # x_t = R x_s + t, shuffled
    T_est, seconds = BASELINES[name](source, target, BaselineParams.unit_box())
    re, te = transform_errors(T_est, T)
    assert T_est.shape == (4, 4) and seconds > 0
    assert re < 0.5 and te < 0.005, f"{name}: RE {re:.3f} deg, TE {te:.4f}"


def test_truth_reference_settles_where_the_geometry_does():
    """`truth+gicp` is given a recorded pose 1 deg off the clouds' true alignment (scipy): it moves to the true
    alignment, so its error against the record is the record's own error."""
    rng = np.random.default_rng(1)
    source = 3.0 * _bumpy_surface(20000, rng)  # metres
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(20.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    T[:3, 3] = [0.4, -0.2, 0.1]
    target = source @ T[:3, :3].T + T[:3, 3]
    c = source.mean(axis=0)
    off = np.eye(4)  # 1 deg about an axis through the source centroid
    off[:3, :3] = Rotation.from_rotvec(np.deg2rad(1.0) * np.array([1.0, 0.0, 0.0])).as_matrix()
    off[:3, 3] = c - off[:3, :3] @ c
    T_est, _ = truth_gicp(source, target, BaselineParams.metric_scene(), T @ off)
    assert transform_errors(T_est, T)[0] < 0.2
    assert transform_errors(T_est, T @ off)[0] == pytest.approx(1.0, abs=0.2)
    # a reference for real frames only: synthetic objects' truth is exact
    assert DATASETS["redkitchen-kidnap-gap90"].applies("truth+gicp")
    assert not DATASETS["modelnet-rpmnet-unseen"].applies("truth+gicp")


def test_scaled_params_multiply_lengths_only():
    p = BaselineParams.unit_box()
    q = p.scaled(4.0)
    assert q.icp_max_distance == 4 * p.icp_max_distance and q.fpfh_radius == 4 * p.fpfh_radius
    assert q.gicp_voxel_size == 4 * p.gicp_voxel_size and q.icp_max_iterations == p.icp_max_iterations


def test_select_indices_spreads_over_the_set():
    assert select_indices(10, None) == list(range(10))
    assert select_indices(5, 8) == list(range(5))
    assert select_indices(101, 5) == [0, 25, 50, 75, 100]


def _rec(method, re, te, cd, seconds, success, **extra):
    return {"dataset": "d", "pair": 0, "method": method, "re_deg": re, "te": te, "cd": cd, "seconds": seconds,
            "success": success, **extra}


def test_summary_math_on_hand_made_records():
    nan = float("nan")
    records = [
        _rec("icp-p2p", 1.0, 0.01, 0.1, 0.010, True),
        _rec("icp-p2p", 3.0, 0.20, 0.3, 0.030, False),
        _rec("icp-p2p", nan, nan, nan, nan, False, error="RuntimeError: boom"),
        _rec("identity", 10.0, 0.5, 0.6, 0.0, False),
    ]
    rows = {r["method"]: r for r in report.summarize(records, cd_floor=[0.05, 0.07, 0.09])}
    assert list(rows) == ["ground truth", "identity", "icp-p2p"]
    assert math.isclose(rows["ground truth"]["cd"], 0.07)
    icp = rows["icp-p2p"]
    assert icp["pairs"] == 3 and icp["errors"] == 1
    assert math.isclose(icp["re_mean"], 2.0) and math.isclose(icp["re_median"], 2.0)
    assert math.isclose(icp["te_mean"], 0.105) and math.isclose(icp["cd"], 0.2)
    assert math.isclose(icp["success"], 1 / 3) and math.isclose(icp["ms_median"], 20.0)


def test_roc_auc_and_threshold_split_on_hand_made_numbers():
    # Successes 0.9, 0.3; failures 0.8, 0.2: pairs (s > f) = (0.9>0.8, 0.9>0.2, 0.3>0.2) = 3 of 4.
    assert math.isclose(report.roc_auc([0.9, 0.8, 0.3, 0.2], [True, False, True, False]), 0.75)
    assert math.isclose(report.roc_auc([0.5, 0.5], [True, False]), 0.5)  # a tie counts one half
    assert math.isclose(report.roc_auc([0.9, 0.1], [True, False]), 1.0)
    assert report.roc_auc([0.9, 0.8], [True, True]) is None
    split = report.confidence_split([0.9, 0.8, 0.3, 0.2], [True, False, True, False], threshold=0.5)
    assert split == {"threshold": 0.5, "n_above": 2, "n_below": 2, "success_above": 0.5, "success_below": 0.5}


# Bounds on the smoke suite's pairs (3 per dataset at most, seed 0), against each pair's known transform.
# Measured: GenReg alone 0.47-1.01 deg on the unseen-category pairs (mean 0.69), GenReg + ICP 0.07-0.31 on
# them and 0.26-0.29 on the FMR-style scene pairs.
MAX_MEAN_RE = {("genreg", "modelnet-unseen-clean"): 1.5, ("genreg+icp", "modelnet-unseen-clean"): 0.6,
               ("genreg", "redkitchen-fmr"): 1.5, ("genreg+icp", "redkitchen-fmr"): 0.6}


def test_smoke_suite_end_to_end_on_the_shipped_models(tmp_path, run_bench_cli):
    """`genreg-bench --suite smoke` with the shipped checkpoints, in its own process (its thread settings
    apply before OpenMP loads): every method on every pair, GenReg within bounds of the truth."""
    proc, data = run_bench_cli(["--suite", "smoke", "--threads", "2", "--no-progress", "--max-pairs", "3"],
                               tmp_path, timeout=300)
    assert "smoke suite:" in proc.stdout and "with 2 threads" in proc.stdout
    assert data["meta"]["checkpoints"] == {"object": "modelnet40_dgcnn", "scene": "7scenes"}
    threads = data["meta"]["threads"]
    assert threads["requested"] == threads["torch"] == 2 and threads["OMP_NUM_THREADS"] == "2"
    assert threads["OMP_WAIT_POLICY"] == "PASSIVE" and not data["skipped"]
    names = list(data["datasets"])
    methods = set(data["meta"]["methods"])
    assert {"genreg", "genreg+icp", "icp-p2p", "fpfh+ransac+icp", "small_gicp"} <= methods
    pairs = sum(d["pairs"] for d in data["datasets"].values())
    assert len(data["records"]) == pairs * len(methods)
    for r in data["records"]:
        assert r["re_deg"] is not None and r["re_deg"] >= 0 and "error" not in r, r
        if r["method"].startswith("genreg"):
            assert 0.0 <= r["confidence"] <= 1.0 and r["timings"]["network"] > 0
    for (method, dataset), bound in MAX_MEAN_RE.items():
        rs = [r for r in data["records"] if r["method"] == method and r["dataset"] == dataset]
        assert len(rs) >= 2 and all(r["success"] for r in rs)
        mean = float(np.mean([r["re_deg"] for r in rs]))
        assert mean < bound, f"{method} on {dataset}: mean RE {mean:.2f} deg (bound {bound})"
    assert data["throughput"] and all(t["ms_per_pair_batched"] > 0 and t["num_points"] == 512
                                      for t in data["throughput"])
    md = (tmp_path / "report.md").read_text()
    assert "Threads: 2" in md and "## Confidence" in md and "success if conf >= 0.9" in md
    for name in names:
        assert DATASETS[name].title in md
    for png in ("re_cdf.png", "accuracy_vs_time.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pair_truth_scores_the_true_pose_at_the_floor():
    """The truth of a hand-made pair: zero error at the true pose, the CD floor there; a known offset."""
    rng = np.random.default_rng(0)
    source = _bumpy_surface(5000, rng)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    target = source @ T[:3, :3].T + T[:3, 3]
    truth = pair_truth({"source": source, "target": target, "transform": T}, 7, BenchOptions(cd_points=1000))
    assert isinstance(truth, PairTruth) and len(truth.source_cd) == len(truth.target_cd) == 1000
    re, te, cd = truth.errors(T)
    assert re < 1e-6 and te < 1e-12 and math.isclose(cd, truth.cd_floor)
    shifted = T.copy()
    shifted[:3, 3] += [0.03, 0.0, 0.04]
    assert math.isclose(truth.errors(shifted)[1], 0.05, rel_tol=1e-9)
    assert all(math.isnan(x) for x in truth.errors(np.full((4, 4), np.nan)))


def test_missing_checkpoint_skips_genreg_with_a_message(tmp_path):
    messages: list[str] = []
    try:
        run = run_benchmark(Suite({"modelnet-unseen-clean": 1}), {"object": str(tmp_path / "absent.pt")},
                            methods=["identity", "genreg", "genreg+icp", "icp-p2p"], progress=False,
                            log=messages.append)
    except DataNotFoundError as exc:
        pytest.skip(f"benchmark data missing: {exc}")
    assert len(messages) == 1 and "GenReg skipped on object datasets" in messages[0]
    assert "checkpoint not found" in messages[0] and run.skipped == messages
    assert {r["method"] for r in run.records} == {"identity", "icp-p2p"}
    assert "Skipped" in report.markdown(run) and "GenReg skipped" in report.markdown(run)


# The partial-overlap datasets, overlap share, symmetric-category means and KISS-Matcher.


def _built(name: str, **options):
    try:
        return DATASETS[name].build(BenchOptions(**options))
    except DataNotFoundError as exc:
        pytest.skip(f"benchmark data missing: {exc}")


def _nn_distance(source: np.ndarray, target: np.ndarray, T: np.ndarray, q: float = 0.5) -> float:
    """Quantile q of the distances from the source points moved by T (x_t = R x_s + t, written out here) to
    their nearest target points."""
    moved = np.asarray(source, dtype=np.float64) @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
    return float(np.quantile(cKDTree(target).query(moved)[0], q))


def test_rpmnet_datasets_are_partial_pairs_at_the_unit_sphere_scale():
    from genreg_core.data import load_modelnet40

    names = {"seen": set(), "unseen": set()}
    for cats, found in names.items():
        pairs = _built(f"modelnet-rpmnet-{cats}")
        shapes = load_modelnet40("test", cats)
        assert len(pairs) == len(shapes)
        for i in (0, len(pairs) // 2, len(pairs) - 1):
            item = pairs[i]
            found.add(item["category"])
            assert item["source"].shape == item["target"].shape == (538, 3)  # ceil(0.7 * 768)
            shape = shapes.points[i].astype(np.float64)
            assert np.linalg.norm(shape, axis=1).max() <= 1.0 + 1e-3  # stored unit-sphere scale
            # The source is a noisy part of the stored shape: every point within the noise clip of it.
            assert cKDTree(shape).query(item["source"])[0].max() <= 0.05 * math.sqrt(3) + 1e-6
            # The truth moves the source onto the target's surface, and the clouds overlap partially.
            assert _nn_distance(item["source"], item["target"], item["transform"]) < 0.05
            re, te = transform_errors(np.asarray(item["transform"]), np.eye(4))
            assert re <= 45 * math.sqrt(3) and te <= 0.5 * math.sqrt(3)
        assert np.array_equal(_built(f"modelnet-rpmnet-{cats}")[0]["source"], pairs[0]["source"])  # seeded
    labels = load_modelnet40("test", "seen").class_names
    assert names["seen"] <= set(labels[:20]) and names["unseen"] <= set(labels[20:])
    spec = DATASETS["modelnet-rpmnet-unseen"]
    assert spec.units == "unit sphere" and spec.success(4.9, 10.0) and not spec.success(5.1, 0.0)
    assert spec.kind == "object" and not spec.applies("fpfh+ransac+icp-accurate")


@pytest.mark.parametrize("name, gap, sequences", [
    ("redkitchen-kidnap-gap30", 30, ["redkitchen"]), ("redkitchen-kidnap-gap60", 60, ["redkitchen"]),
    ("redkitchen-kidnap-gap90", 90, ["redkitchen"]), ("sun3d-kidnap-gap5", 5, ["sun3d-1", "sun3d-2"]), ("sun3d-kidnap-gap20", 20, ["sun3d-1", "sun3d-2"]),
])
def test_kidnap_datasets_truth_puts_the_moved_source_onto_the_target(name, gap, sequences):
    from genreg_core.data import RGBDSequence

    pairs = _built(name, frame_stride=4)
    seqs = [RGBDSequence.open(s) for s in sequences]
    frames = [[i for i in s.frame_indices if i + gap in s and (s.name != "redkitchen" or 800 <= i < 1000 - gap)]
              for s in seqs]
    assert len(pairs) == sum(len(f) for f in frames)
    for k in (0, len(pairs) - 1):
        item = pairs[k]
        seq = seqs[0] if k < len(frames[0]) else seqs[-1]
        i = item["target_index"]
        assert item["source_index"] == i + gap
        raw = seq.points(i + gap, 4).astype(np.float64)
        M = np.asarray(item["kidnap"])
        angle = np.rad2deg(Rotation.from_matrix(M[:3, :3]).magnitude())
        centroid = raw.mean(axis=0)
        shift = np.linalg.norm(M[:3, :3] @ centroid + M[:3, 3] - centroid)  # the centroid moves by t only
        assert 0 <= angle <= 45 + 1e-6 and shift <= 0.5 + 1e-6
        assert np.allclose(item["source"], raw @ M[:3, :3].T + M[:3, 3], atol=1e-4)
        # Truth = frame truth after undoing the kidnap; it registers the moved source onto the target.
        assert np.allclose(np.asarray(item["transform"]) @ M, seq.relative_pose(i + gap, i), atol=1e-5)
        # The first quartile stays inside the overlap (>= 40 %): within the target's own point spacing.
        near = _nn_distance(item["source"], item["target"], item["transform"], 0.25)
        ignored = _nn_distance(item["source"], item["target"], seq.relative_pose(i + gap, i), 0.25)
        spacing = float(np.median(cKDTree(item["target"]).query(item["target"], k=2)[0][:, 1]))
        assert near < 2 * spacing
        if np.linalg.norm(item["source"] - raw, axis=1).mean() > 0.1:  # a kidnap that moves the cloud matters
            assert near < 0.75 * ignored
    spec = DATASETS[name]
    assert spec.units == "m" and spec.success(1.9, 0.049) and not spec.success(1.9, 0.051)


def test_overlap_share_matches_an_independent_count():
    """The stored overlap share against counting, over every source point, the ones with a target point
    within the radius at the true pose (scipy ball queries here, nearest distances in the bench)."""
    item = _built("redkitchen-kidnap-gap30", frame_stride=4)[5]
    truth = pair_truth(item, 5, BenchOptions(), overlap_radius=0.05)
    moved = item["source"].astype(np.float64) @ item["transform"][:3, :3].T + item["transform"][:3, 3]
    hits = cKDTree(item["target"]).query_ball_point(moved, 0.05, return_length=True)
    share = float(np.mean(hits > 0))
    assert 0.0 <= truth.overlap <= 1.0 and 0.05 < share < 0.999
    assert abs(truth.overlap - share) < 0.03  # the bench counts 4096 random source points
    obj = _built("modelnet-rpmnet-unseen")[3]
    truth = pair_truth(obj, 3, BenchOptions(), overlap_radius=0.05)  # 538 points: all of them counted
    moved = obj["source"].astype(np.float64) @ obj["transform"][:3, :3].T + obj["transform"][:3, 3]
    exact = float(np.mean(cKDTree(obj["target"]).query_ball_point(moved, 0.05, return_length=True) > 0))
    assert math.isclose(truth.overlap, exact) and 0.2 < exact < 1.0
    assert pair_truth(obj, 3, BenchOptions()).overlap is None


def test_kiss_matcher_registers_a_scene_pair_with_a_rigid_transform():
    """KISS-Matcher + point-to-plane on a kidnapped redkitchen pair (quarter resolution): a rotation matrix,
    and the pair registered to its truth."""
    item = _built("redkitchen-kidnap-gap30", frame_stride=2)[20]
    T, seconds = BASELINES["kiss-matcher+p2plane"](item["source"], item["target"], BaselineParams.metric_scene())
    R = T[:3, :3]
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1]) and seconds > 0
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-6)
    re, te = transform_errors(T, np.asarray(item["transform"], dtype=np.float64))
    assert re < 2.0 and te < 0.05, f"RE {re:.2f} deg, TE {te:.3f} m"


def test_symmetric_means_and_overlap_bins_on_hand_made_records():
    recs = [_rec("genreg", 1.0, 0.01, 0.1, 0.01, True, category="airplane", overlap=0.95),
            _rec("genreg", 3.0, 0.03, 0.1, 0.01, True, category="chair", overlap=0.5),
            _rec("genreg", 170.0, 0.5, 0.1, 0.01, False, category="bowl", overlap=0.55)]
    row = report.summarize(recs)[0]
    assert math.isclose(row["re_mean"], 58.0) and row["asymmetric"]["pairs"] == 2
    assert math.isclose(row["asymmetric"]["re_mean"], 2.0) and math.isclose(row["asymmetric"]["te_mean"], 0.02)
    assert row["asymmetric"]["success"] == 1.0
    assert [report.overlap_bin(x) for x in (0.0, 0.19, 0.2, 0.95, 1.0)] == [0, 0, 1, 4, 4]
    cells = report.success_by_overlap(recs)["genreg"]
    assert cells[2] == (2, 0.5) and cells[4] == (1, 1.0) and cells[0][0] == 0
    assert "RE mean w/o sym." in report.dataset_table([row], "unit sphere")
    assert report.success_text({"max_re_deg": 5.0, "max_te": None}) == "RE < 5 deg"


def test_partial_suite_plan_and_dataset_checks():
    from genreg_bench.datasets import PARTIAL_METHODS, SUITES, plan_suite, resolve_suite

    suite = SUITES["partial"]
    assert set(suite.counts) == {"modelnet-rpmnet-seen", "modelnet-rpmnet-unseen", "redkitchen-kidnap-gap30",
                                 "redkitchen-kidnap-gap60", "redkitchen-kidnap-gap90", "sun3d-kidnap-gap5",
                                 "sun3d-kidnap-gap20"}
    # The added gaps as many pairs as their siblings, kidnapped, on the validation frames / both SUN3D fragments.
    assert suite.counts["redkitchen-kidnap-gap90"] == suite.counts["redkitchen-kidnap-gap30"] == 12
    assert suite.counts["sun3d-kidnap-gap20"] == suite.counts["sun3d-kidnap-gap5"] == 5
    assert DATASETS["redkitchen-kidnap-gap90"].frame == DATASETS["redkitchen-kidnap-gap30"].frame
    assert suite.methods == PARTIAL_METHODS and "kiss-matcher+p2plane" in PARTIAL_METHODS
    assert resolve_suite("partial", None)[2].frame_stride == 1
    assert resolve_suite("smoke", None)[2].frame_stride == 4
    assert resolve_suite("smoke", BenchOptions(frame_stride=2))[2].frame_stride == 2  # the caller's wins
    with pytest.raises(ValueError, match="suites holding them"):
        plan_suite("quick", None, ["sun3d-kidnap-gap5"], 1)


def test_report_writes_overlap_table_and_plot(tmp_path):
    from genreg_bench.runner import BenchRun

    recs = [_rec(m, re, 0.01, 0.1, 0.01, re < 2, overlap=ov, pair=k)
            for k, ov in enumerate((0.3, 0.5, 0.9)) for m, re in (("genreg", 3 * ov), ("icp-p2plane", 5.0))]
    meta = {"suite": "custom", "date": "now", "machine": {"cpu_count": 2, "torch": "x"},
            "threads": {"requested": 2, "torch": 2, "OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE",
                        "small_gicp": 2},
            "checkpoints": {"object": "o", "scene": "s"}, "options": {"cd_points": 4096}}
    info = {"title": "D", "kind": "scene", "units": "m", "checkpoint": "s", "success": {"max_re_deg": 2.0, "max_te": 0.05},
            "pairs": 3, "available_pairs": 3, "points_per_cloud": 10, "genreg": True, "cd_floor": [0.1] * 3,
            "overlap": [0.3, 0.5, 0.9], "overlap_radius": 0.05}
    paths = report.write_report(BenchRun(meta, {"d": info}, recs, [], []), tmp_path)
    md = paths["markdown"].read_text()
    assert "Success by overlap share" in md and "| genreg | – | 100% | 100% | – | 0% |" in md
    assert "overlap share (within 0.05 m) mean 0.57, range 0.30-0.90" in md
    assert paths["success_vs_overlap"].read_bytes()[:4] == b"\x89PNG"


def test_partial_suite_cli_on_object_pairs(tmp_path, run_bench_cli):
    """`genreg-bench --suite partial` on two RPM-Net-style pairs: the suite's methods, overlap and category per
    record, the symmetric-category columns, the checkpoint flag."""
    proc, data = run_bench_cli(["--suite", "partial", "--datasets", "modelnet-rpmnet-unseen", "--max-pairs", "2",
                                "--object-checkpoint", "modelnet40", "--threads", "2", "--no-progress"],
                               tmp_path, timeout=240)
    assert "partial suite:" in proc.stdout and data["meta"]["checkpoints"]["object"] == "modelnet40"
    info = data["datasets"]["modelnet-rpmnet-unseen"]
    assert info["units"] == "unit sphere" and info["success"]["max_te"] is None and info["pairs"] == 2
    assert info["methods"] == [m for m in data["meta"]["methods"] if m not in SCENE_ONLY_METHODS]
    assert "kiss-matcher+p2plane" in info["methods"] and "genreg+p2plane" in info["methods"]
    assert len(data["records"]) == 2 * len(info["methods"])
    for r in data["records"]:
        assert 0.0 <= r["overlap"] <= 1.0 and r["category"] and "error" not in r, r
    md = (tmp_path / "report.md").read_text()
    assert "RE mean w/o sym." in md
    # GenReg rows carry the calibration columns, baselines dashes; the reliability diagram is written and linked.
    assert report.CALIBRATION_HEAD in md and "(reliability.png)" in md
    genreg_row = next(line for line in md.splitlines() if line.startswith("| genreg | "))
    assert genreg_row.count(" of ") == 1 and "at >= 0.5 |" in genreg_row
    assert next(line for line in md.splitlines() if line.startswith("| identity | ")).endswith("| – | – | – |")
    assert (tmp_path / "reliability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ece_and_confident_wrong_on_hand_made_numbers():
    # Bins of width 0.1: 0.05 and 0.15 (one failure each), 0.92 and 0.98 (success, failure): 1, 1, 2 of 4.
    p = [0.05, 0.15, 0.92, 0.98]
    y = [False, False, True, False]
    # |0 - 0.05| / 4 + |0 - 0.15| / 4 + |0.5 - 0.95| * 2 / 4 = 0.0125 + 0.0375 + 0.225
    assert math.isclose(report.expected_calibration_error(p, y), 0.275)
    assert report.confident_wrong(p, y) == (1, 2) and report.confident_wrong(p, y, threshold=0.1) == (2, 3)
    # Perfectly calibrated bins: 0.25 succeeds 1 in 4, 0.75 succeeds 3 in 4, 1.0 (the closed last bin) always.
    p = [0.25] * 4 + [0.75] * 4 + [1.0] * 2
    y = [True, False, False, False, True, True, True, False, True, True]
    assert math.isclose(report.expected_calibration_error(p, y), 0.0, abs_tol=1e-12)
    cells = report.reliability_bins(p, y)
    assert len(cells) == 10 and cells[2] == (4, 0.25, 0.25) and cells[9] == (2, 1.0, 1.0) and cells[0][0] == 0
    assert math.isnan(report.expected_calibration_error([], []))
    # One class only: no AUC, a dash in the table.
    stats = report.calibration_stats([0.9, 0.8, 0.2], [True, True, True])
    assert stats["auc"] is None and stats == {**stats, "confident_wrong": 0, "confident": 2}
    assert report._calibration_cells(stats).startswith(" – | ")


def test_report_gains_calibration_columns_and_reliability_diagram(tmp_path):
    """Hand-made records of a kidnapped-pair table: GenReg rows with confidences get AUC, ECE and the
    confident-wrong count, the baseline dashes; the confidence section the same; reliability.png linked."""
    from genreg_bench.runner import BenchRun

    conf = (0.95, 0.9, 0.7, 0.6, 0.2)
    good = (True, True, False, True, False)
    recs = [_rec("genreg", 1.0 if ok else 9.0, 0.01, 0.1, 0.01, ok, confidence=c, pair=k)
            for k, (c, ok) in enumerate(zip(conf, good))]
    recs += [_rec("genreg+icp", 1.0, 0.01, 0.1, 0.01, True, confidence=0.9, pair=k) for k in range(5)]
    recs += [_rec("icp-p2plane", 5.0, 0.01, 0.1, 0.01, False, pair=k) for k in range(5)]
    meta = {"suite": "custom", "date": "now", "machine": {"cpu_count": 2, "torch": "x"},
            "threads": {"requested": 2, "torch": 2, "OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE",
                        "small_gicp": 2},
            "checkpoints": {"object": "o", "scene": "s"}, "options": {"cd_points": 4096}}
    info = {"title": "D", "kind": "scene", "units": "m", "checkpoint": "s", "success": {"max_re_deg": 2.0, "max_te": 0.05},
            "pairs": 5, "available_pairs": 5, "points_per_cloud": 10, "genreg": True, "cd_floor": [0.1] * 5}
    paths = report.write_report(BenchRun(meta, {"d": info}, recs, [], []), tmp_path)
    md = paths["markdown"].read_text()
    ece = report.expected_calibration_error(conf, good)
    # AUC: successes 0.95, 0.9, 0.6 against failures 0.7, 0.2: 5 of 6 pairs ordered.
    assert f"| {0.8333:.3f} | {ece:.3f} | 1 of 4 at >= 0.5 |" in md
    assert "| genreg+icp | " in md and "| – | 0.100 | 0 of 5 at >= 0.5 |" in md  # one class: no AUC
    assert next(line for line in md.splitlines() if line.startswith("| icp-p2plane | ")).endswith("| – | – | – |")
    assert report.CALIBRATION_HEAD in md and "| ROC AUC | ECE | confident-wrong |" in md
    assert "![reliability diagram](reliability.png)" in md
    assert paths["reliability"] == tmp_path / "reliability.png"
    assert paths["reliability"].read_bytes()[:4] == b"\x89PNG"
    row = report.to_json(BenchRun(meta, {"d": info}, recs, [], []))["confidence"][0]
    assert row["confident_wrong"] == 1 and row["confident"] == 4 and math.isclose(row["ece"], ece)


def test_pairs_flag_sets_every_dataset_count_and_keeps_the_suite_name():
    """`--pairs N` replaces the suite's per-dataset counts (an evenly spread N of each, all when a set holds
    fewer); the report keeps the suite's name and its methods."""
    from genreg_bench.cli import parse_args
    from genreg_bench.datasets import SUITES, resolve_suite

    args = parse_args(["--suite", "partial", "--pairs", "48", "--out", "x"])
    suite = SUITES[args.suite].with_pairs(args.suite, args.pairs)
    name, resolved, _ = resolve_suite(suite, None)
    assert name == "partial" and resolved.methods == SUITES["partial"].methods
    assert set(resolved.counts.values()) == {48} and set(resolved.counts) == set(SUITES["partial"].counts)
    assert SUITES["partial"].counts["sun3d-kidnap-gap5"] == 5  # the suite itself is untouched


def test_every_genreg_method_carries_the_models_calibration_and_scenes_refine_as_the_node():
    from genreg_bench.methods import load_genreg
    from genreg_core.config import SCENE_REGISTRATION

    methods = load_genreg("7scenes", 0, SCENE_REGISTRATION)
    assert all(reg.calibration is not None for reg in methods.values())
    calibrated = {name for name, reg in methods.items() if reg.calibrated}  # the scene model's: not point-to-point
    assert calibrated == {"genreg", "genreg+p2plane", "genreg+gicp", "genreg+p2plane+fallback"}
    assert methods["genreg+gicp"].config.refine == SCENE_REGISTRATION.refine  # GICP, 20 iterations
