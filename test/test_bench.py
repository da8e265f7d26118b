"""Benchmark harness: baselines recover a known transform, the smoke suite runs end to end on the shipped
models (`modelnet40`, `7scenes`) and registers its pairs to their known truth, report math."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from genreg_core.bench import report
from genreg_core.bench.baselines import BASELINES, BaselineParams
from genreg_core.bench.datasets import DATASETS, BenchOptions, PairTruth, Suite, pair_truth, select_indices
from genreg_core.bench.runner import run_benchmark
from genreg_core.errors import DataNotFoundError
from genreg_core.metrics import transform_errors

REPO = Path(__file__).resolve().parent.parent


def _bumpy_surface(n: int, rng: np.random.Generator) -> np.ndarray:
    """An asymmetric height field in the unit box: curvature everywhere, so FPFH and ICP lock on."""
    x, y = rng.random(n), rng.random(n)
    z = (0.25 * np.sin(3 * x) * np.cos(2 * y) + 0.3 * np.exp(-((x - 0.3) ** 2 + (y - 0.7) ** 2) / 0.02)
         - 0.2 * np.exp(-((x - 0.75) ** 2 + (y - 0.25) ** 2) / 0.03) + 0.3)
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("name", sorted(BASELINES))
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
    assert data["meta"]["checkpoints"] == {"object": "modelnet40", "scene": "7scenes"}
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
