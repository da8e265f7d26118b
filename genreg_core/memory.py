"""Process memory policy of genreg's own entry points: keep freed memory for reuse.

glibc's malloc serves blocks above its mmap threshold with fresh mappings and returns freed memory at the
top of the heap to the system once more than its trim threshold is free. The network, ICP and training's
PDSAC allocate and free a few MB per stage, so by default every call maps fresh pages and faults them in
again: training's PDSAC at N = 512 faults 865-4,430 pages per call (glibc moves its thresholds as blocks are
freed, so the figure varies by process; 8,717 with the thresholds held at their start), and a fifth to a
third of a training process's CPU time went to the kernel. `retain_freed_memory` serves every block from the
heap (no mappings: glibc still maps when the heap cannot grow) and keeps freed memory there for reuse: after
it, training's PDSAC faults 0-53 pages per call (`test_memory.py`), and 15 training iterations fault 7x less
(sys time 6.9 -> 1.6 s). Inference's PDSAC (compiled, `genreg_core.kernels`) allocates no large table and
faults none either way. The cost is that the resident size stays at its peak instead of shrinking between
registrations.

`genreg-train`, `genreg-bench`, `register_node` and the benchmark scripts call it at start-up; a program
using the registration API can call it too (or set MALLOC_TRIM_THRESHOLD_=1073741824 and MALLOC_MMAP_MAX_=0
in the environment). Without glibc it does nothing.
"""

from __future__ import annotations

import ctypes

M_TRIM_THRESHOLD = -1  # glibc mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
M_MMAP_MAX = -4
MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's largest (fixes the threshold: no dynamic trim threshold either)
TRIM_THRESHOLD_BYTES = 1 << 30  # free memory at the heap's top returned to the system only above 1 GiB


def retain_freed_memory() -> bool:
    """Set glibc's malloc to keep freed memory for reuse (module docstring). True if applied, False
    without glibc's mallopt."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return all([mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), mallopt(M_MMAP_MAX, 0),
                mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)])
