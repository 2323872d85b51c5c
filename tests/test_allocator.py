"""rtsgt.allocator: glibc's malloc keeps the memory a large array frees (docs/benchmarks.md)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(
    platform.libc_ver()[0] != "glibc" or not Path("/proc/self/statm").exists(),
    reason="glibc's mallopt, Linux's /proc")

MIB = 1 << 20

# In a process of its own (the setting is the process's for the rest of its life): the
# resident memory a freed array of 28 MiB leaves, then the page faults of filling arrays of
# 20-28 MiB one after another, then (after one of 100 MiB) of 96-100 MiB: above the largest
# threshold glibc allows for taking a block from the heap, mapped on its own unless mapping
# is off
_PROBE = """
import os, resource, sys
import numpy as np
from rtsgt.allocator import keep_freed_memory, limit_arenas
ok = keep_freed_memory() if sys.argv[1] == "keep" else True
ok &= limit_arenas()
def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
def faults(n):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(n // 8)
    a += 1.0
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
before = resident()
faults(28 << 20)
kept = resident() - before
small = max(faults(m << 20) for m in (20, 28, 24, 22, 26))
faults(100 << 20)  # the heap grown to it once
print(int(ok), kept, small, max(faults(m << 20) for m in (96, 100, 98)))
"""


def _probe(mode: str) -> tuple[bool, int, int, int]:
    env = dict(os.environ, NUMPY_MADVISE_HUGEPAGE="0")
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True,
                         env=env, check=True, timeout=120).stdout.split()
    return bool(int(out[0])), int(out[1]), int(out[2]), int(out[3])


def test_freed_memory_is_kept_and_reused_not_faulted_in_again():
    ok, kept, faults, large = _probe("keep")
    assert ok
    assert kept > 24 * MIB  # the freed 28 MiB stay in the process
    assert faults < 0.05 * (28 * MIB // 4096)  # and are reused: next to no page faults
    assert large < 0.05 * (96 * MIB // 4096)  # so are arrays above glibc's largest threshold
    # glibc's own thresholds: the first large array is mapped on its own and returned, and
    # each of 96-100 MiB is mapped and faulted in afresh
    ok, kept, _, large = _probe("default")
    assert ok
    assert kept < 4 * MIB
    assert large > 0.5 * (96 * MIB // 4096)
