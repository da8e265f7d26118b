"""scripts/bench_lidar_pairs.py: the truth of its pairs, checked on the scans themselves (the source moved by it
lies on the target's surfaces, and moved by a pose 2 m off along the path it does not)."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from genreg_core.data import lidar_world as lw
from genreg_core.geometry import apply_transform, make_transform

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture()
def bench(monkeypatch):
    # importing the script sets these; restored after the test
    monkeypatch.setenv("OMP_WAIT_POLICY", os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    monkeypatch.setenv("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "2"))
    monkeypatch.syspath_prepend(str(REPO / "scripts"))
    spec = importlib.util.spec_from_file_location("bench_lidar_pairs", REPO / "scripts" / "bench_lidar_pairs.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_lidar_pairs", module)
    spec.loader.exec_module(module)
    return module


def median_gap(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> float:
    """The median distance from the source's points moved by T to the target's nearest point, m."""
    return float(np.median(cKDTree(target).query(apply_transform(T, source))[0]))


def test_a_street_pair_and_a_corridor_pair_are_laid_on_each_other_by_their_truth(bench):
    world = lw.campus_world(0, blocks=(1, 1))
    for kind, d in (("road", 6.0), ("corridor", 2.0)):
        ((distance, source, target, truth),) = bench.pairs(world, kind, [d], 1, 0)
        assert distance == d
        step = make_transform(np.eye(3), np.array([2.0, 0.0, 0.0]))  # 2 m along the path (the target heads along it)
        assert median_gap(source, target, truth) < 0.1 and median_gap(source, target, step @ truth) > 0.4, kind


def test_the_car_pairs_truth_lays_scan_401_on_400_at_every_turn(bench):
    car = bench.car_pairs()
    if not car:
        pytest.skip("libpointmatcher's car pair is not in GENREG_DATA")
    assert len(car) == 8
    turned = car[2]  # by 90 deg
    for source, target, truth in (car[0], turned):
        assert median_gap(source, target, truth) < 0.15  # the scans' rings are 0.1-1 m apart
    assert median_gap(turned[0], turned[1], car[0][2]) > 0.4  # the unturned truth does not fit the turned scan
