"""genreg_core.memory: with freed memory retained, PDSAC stops faulting fresh pages in on every call."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = """
import resource, sys, torch
torch.set_num_threads(1)
from genreg_core.memory import retain_freed_memory
if sys.argv[1] == "retain":
    assert retain_freed_memory()
from genreg_core.config import PDSACConfig
from genreg_core.pdsac import pdsac_bidirectional
g = torch.Generator().manual_seed(0)
a, b = torch.rand(1, 512, 3, generator=g), torch.rand(1, 512, 3, generator=g)
overlap = (torch.rand(1, 512, generator=g), torch.rand(1, 512, generator=g))
cfg = PDSACConfig(inlier_threshold=0.05)
for _ in range(3):
    pdsac_bidirectional(a, b, b, a, cfg, g, overlap)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    pdsac_bidirectional(a, b, b, a, cfg, g, overlap)
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def _faults_per_call(mode: str) -> float:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")} | {"OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True, env=env)
    return float(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_retained_memory_removes_pdsacs_page_faults():
    default, retained = _faults_per_call("default"), _faults_per_call("retain")
    assert default > 200  # fresh pages on every call: the cost retain_freed_memory removes
    assert retained < 50 and retained < default / 10
