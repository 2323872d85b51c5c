"""The process's memory allocator (glibc's ``malloc``), set for rtsgt's large numpy arrays.

Two settings, each nothing where the C library is not glibc: at most :data:`MALLOC_ARENAS`
arenas (the command line's threads keep less freed memory), and freed memory kept in the
process (the joint engine's arrays of tens to hundreds of megabytes, allocated at every
Gauss-Newton step, no longer mapped afresh and faulted in page by page). Measured in
docs/benchmarks.md#speed.
"""

from __future__ import annotations

import ctypes

#: The most malloc arenas the command line runs with.
MALLOC_ARENAS = 2
#: Blocks up to this size come from the heap rather than from their own ``mmap`` (glibc's
#: largest allowed on 64-bit systems), bytes.
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Freed memory at the heap's top kept in the process up to this size, bytes.
TRIM_THRESHOLD = 1024 * 1024 * 1024

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -3, -4, -8


def _mallopt(param: int, value: int) -> bool:
    """glibc's ``mallopt(param, value)``; False where it failed or there is no glibc."""
    try:
        return bool(ctypes.CDLL(None).mallopt(param, value))
    except (AttributeError, OSError, TypeError):  # not glibc
        return False


def limit_arenas(n: int = MALLOC_ARENAS) -> bool:
    """At most ``n`` malloc arenas for the rest of the process; whether it was set."""
    return _mallopt(_M_ARENA_MAX, n)


def keep_freed_memory() -> bool:
    """For the rest of the process, every block from the heap (``M_MMAP_MAX`` 0: none mapped
    on its own; glibc caps the size up to which it would take one from the heap at
    :data:`MMAP_THRESHOLD`, and an hour's solves use arrays of hundreds of megabytes) and
    freed memory kept up to :data:`TRIM_THRESHOLD` (glibc's adaptive thresholds off): the
    memory a large array frees is reused by the next instead of being returned to the system
    and faulted in again. Whether all three were set. The process's resident size then stays
    near its peak."""
    return (_mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
            & _mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) & _mallopt(_M_MMAP_MAX, 0))


__all__ = ["MALLOC_ARENAS", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory",
           "limit_arenas"]
