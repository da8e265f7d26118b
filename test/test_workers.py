"""Registration in a worker process (genreg_ros.workers): the same results as the core's Registrar in this
process, the core's errors with their class, and a worker that dies is started again."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from genreg_core.config import SCENE_PDSAC, RefineConfig, RegistrationConfig
from genreg_core.data.rgbd import RGBDSequence
from genreg_core.errors import CheckpointError, TooFewPointsError
from genreg_core.registration import Registrar
from genreg_ros.workers import RemoteRegistrar

CONFIG = RegistrationConfig(pdsac=SCENE_PDSAC, refine=RefineConfig(method="gicp", max_iterations=20, num_points=2000))


@pytest.fixture(scope="module")
def remote():
    r = RemoteRegistrar("7scenes", CONFIG)
    r.start()
    r.wait_ready()
    yield r
    r.close()


def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    seq = RGBDSequence.redkitchen()
    return seq.points(801, 4).astype(np.float32), seq.points(800, 4), seq.relative_pose(801, 800)


def test_remote_result_equals_the_in_process_registrar_and_the_truth(remote):
    source, target, T_true = pair()  # float32 source, float64 target: both go through shared memory as given
    registrar = Registrar.from_checkpoint("7scenes", CONFIG)
    local = registrar.register(source, target)
    got = remote.register(source, target)
    assert remote.num_points == registrar.num_points
    np.testing.assert_array_equal(got.transformation, local.transformation)
    np.testing.assert_array_equal(got.aligned_source, local.aligned_source)
    np.testing.assert_array_equal(got.source_valid_mask, local.source_valid_mask)
    assert got.confidence == local.confidence and got.covariance is not None
    E = np.linalg.inv(T_true) @ got.transformation
    assert np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))) < 1.0
    assert np.linalg.norm(E[:3, 3]) < 0.02
    remote.config = RegistrationConfig(refine=RefineConfig(method="none"))  # new settings travel with the next pair
    moved = remote.register(source, target)
    assert not np.array_equal(moved.transformation, got.transformation)
    assert np.array_equal(remote.register(source, target).transformation, moved.transformation)  # and stay
    remote.config = CONFIG
    np.testing.assert_array_equal(remote.register(source, target).transformation, got.transformation)


def test_core_errors_keep_their_class_and_the_worker_carries_on(remote):
    source, target, _ = pair()
    with pytest.raises(TooFewPointsError, match="registration needs at least"):
        remote.register(source[:3], target)
    assert remote.register(source, target).confidence > 0.5


def test_a_killed_worker_is_started_again(remote):
    source, target, _ = pair()
    first = remote.register(source, target)
    os.kill(remote.pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while remote.alive:  # gone between two pairs (a worker that dies during a pair raises WorkerError)
        assert time.monotonic() < deadline
        time.sleep(0.01)
    again = remote.register(source, target)  # a fresh process, the same result
    np.testing.assert_array_equal(again.transformation, first.transformation)


def test_an_unloadable_checkpoint_raises_the_core_error(tmp_path):
    r = RemoteRegistrar(str(tmp_path / "missing.pt"), CONFIG)
    r.start()
    with pytest.raises(CheckpointError, match="not found"):
        r.wait_ready()
    assert r.pid is None  # closed
