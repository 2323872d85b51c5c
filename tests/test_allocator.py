"""rtsgt.allocator: glibc's malloc keeps the memory a large array frees (docs/benchmarks.md)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")

# Page faults of filling arrays of 20-28 MiB one after another, after a first of 28 MiB (in
# a process of its own: the setting is the process's for the rest of its life)
_PROBE = """
import resource, sys
import numpy as np
from rtsgt.allocator import keep_freed_memory, limit_arenas
ok = keep_freed_memory() if sys.argv[1] == "keep" else True
ok &= limit_arenas()
def faults(n):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(n // 8)
    a += 1.0
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
faults(28 << 20)
print(int(ok), max(faults(m << 20) for m in (20, 28, 24, 22, 26)))
"""


def _probe(mode: str) -> tuple[bool, int]:
    env = dict(os.environ, NUMPY_MADVISE_HUGEPAGE="0")  # faults of 4 KiB pages
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True,
                         env=env, check=True, timeout=120).stdout.split()
    return bool(int(out[0])), int(out[1])


def test_freed_memory_is_reused_not_faulted_in_again():
    pages = (28 << 20) // 4096
    ok, faults = _probe("keep")
    assert ok
    assert faults < 0.05 * pages
    # glibc's own adaptive thresholds map the largest afresh: the probe sees the difference
    ok, faults = _probe("default")
    assert ok
    assert faults > 0.5 * pages
