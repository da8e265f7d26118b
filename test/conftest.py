"""Shared fixtures. ROS: every rclpy process of a test run stays on loopback
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in the ROS_DOMAIN_ID of the environment, else a random one
(`genreg_ros.environment.ros_environment`), and ROS tests put their topics under a random namespace, so
parallel test runs on one machine never see each other's messages.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

import pytest

from genreg_ros.environment import FASTDDS_PROFILE, ros_environment

REPO = Path(__file__).resolve().parent.parent

try:  # property-based tests: "ci" (the default) keeps them short and the same on every run (derandomised: a
    # suite that passes passes again), HYPOTHESIS_PROFILE=local runs them long, with new examples each time
    from hypothesis import settings as _hypothesis_settings

    _hypothesis_settings.register_profile("ci", max_examples=300, deadline=None, derandomize=True)
    _hypothesis_settings.register_profile("local", max_examples=10_000, deadline=None)
    _hypothesis_settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
except ImportError:  # hypothesis missing: only the property-based tests need it (they skip)
    pass

@pytest.fixture(scope="session", autouse=True)
def ros_env() -> dict[str, str]:
    """Set the ROS discovery variables for this process and every subprocess it starts; always the shipped
    large-cloud Fast DDS profile, as users are told to run it."""
    env = ros_environment(profile=FASTDDS_PROFILE)
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    yield env
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="session")
def ros_namespace() -> str:
    """A topic namespace unique to this test session."""
    return f"/genreg_test_{secrets.token_hex(4)}"


@pytest.fixture(scope="session")
def fastdds_profile() -> Path:
    """The shipped Fast DDS profile for large clouds."""
    assert FASTDDS_PROFILE.is_file()
    return FASTDDS_PROFILE


@pytest.fixture(scope="session")
def untrained_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small (N=256) randomly initialised GenReg checkpoint: trained weights are not needed to test plumbing."""
    import torch

    from genreg_core.checkpoint import save_checkpoint
    from genreg_core.config import ModelConfig
    from genreg_core.model.genreg import GenRegNet

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "untrained_n256.pt"
    save_checkpoint(GenRegNet(ModelConfig(num_points=256)), path)
    return path


def _reject_constant(name: str) -> None:
    raise ValueError(f"invalid JSON constant {name}")


@pytest.fixture
def run_bench_cli():
    """Run `genreg-bench ARGS --out OUT` in its own process (its thread settings apply before OpenMP
    loads; inherited OMP_* dropped); skip when the benchmark data is missing. Returns (process, results.json
    parsed with NaN/Infinity rejected)."""
    import json
    import subprocess
    import sys

    from genreg_bench.datasets import DATASETS, BenchOptions
    from genreg_core.errors import DataNotFoundError

    try:
        DATASETS["modelnet-unseen-clean"].build(BenchOptions())
    except DataNotFoundError as exc:
        pytest.skip(f"benchmark data missing: {exc}")

    def run(args: list[str], out: Path, timeout: float) -> tuple[subprocess.CompletedProcess, dict]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("OMP_")}
        cmd = [sys.executable, "-m", "genreg_bench.cli", *args, "--out", str(out)]
        proc = subprocess.run(cmd, check=False, env=env, capture_output=True, text=True, timeout=timeout,
                              cwd=Path(__file__).resolve().parent.parent)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc, json.loads((out / "results.json").read_text(), parse_constant=_reject_constant)

    return run
