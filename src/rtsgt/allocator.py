"""The process's memory allocator (glibc's ``malloc``), set for rtsgt's large numpy arrays,
and the memory the process may still take (:func:`available_memory`).

Two settings, each nothing where the C library is not glibc: at most :data:`MALLOC_ARENAS`
arenas (the command line's threads keep less freed memory), and freed memory kept in the
process (the joint engine's arrays of tens to hundreds of megabytes, allocated at every
Gauss-Newton step, no longer mapped afresh and faulted in page by page). Measured in
docs/benchmarks.md#speed.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

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


#: A control group's memory limit at or above this is none (the kernel's "unlimited"), bytes.
NO_LIMIT_BYTES = 1 << 60


def _read_int(path: Path) -> int | None:
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):  # absent, "max", unreadable
        return None


def _meminfo_available(meminfo: Path) -> int | None:
    """``MemAvailable`` of a Linux ``/proc/meminfo``, bytes (None: not there)."""
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_room(proc_cgroup: Path, root: Path) -> int | None:
    """The memory left to the process's control group (its limit minus its use), bytes, from
    its ``/proc/self/cgroup`` and the hierarchy mounted at ``root`` (cgroup v2's
    ``memory.max``, ``memory.current``; v1's ``memory.limit_in_bytes``,
    ``memory.usage_in_bytes``); None where it has no limit or none is readable."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":  # v2
            base, names = root, ("memory.max", "memory.current")
        elif "memory" in controllers.split(","):  # v1
            base, names = root / "memory", ("memory.limit_in_bytes", "memory.usage_in_bytes")
        else:
            continue
        # the group's own files, else the mount's (a container sees its group at the root)
        for where in (base / path.lstrip("/"), base):
            limit, used = (_read_int(where / n) for n in names)
            if limit is not None:
                break
        if limit is not None and limit < NO_LIMIT_BYTES:
            return max(0, limit - (used or 0))
    return None


def available_memory(meminfo: Path = Path("/proc/meminfo"),
                     proc_cgroup: Path = Path("/proc/self/cgroup"),
                     cgroup_root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """The memory this process may still take, bytes: the system's available memory
    (Linux's ``MemAvailable``: free plus reclaimable) or, where less, what its control
    group's limit leaves (a container's); None where neither is known (not Linux)."""
    known = [v for v in (_meminfo_available(meminfo), _cgroup_room(proc_cgroup, cgroup_root))
             if v is not None]
    return min(known) if known else None


__all__ = ["MALLOC_ARENAS", "MMAP_THRESHOLD", "NO_LIMIT_BYTES", "TRIM_THRESHOLD",
           "available_memory", "keep_freed_memory", "limit_arenas"]
