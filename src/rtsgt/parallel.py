"""How many threads rtsgt's numeric stages use: the cores this process may run on.

numpy releases the interpreter lock in its array operations, so the stages that split their
work into independent parts (the prisms' GPs, the leave-one-out candidates, the Monte Carlo
chunks of the poses) run them in threads; their results do not depend on how many.
"""

from __future__ import annotations

import os

__all__ = ["available_cores"]


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform has one, else
    the machine's), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on every platform
        return max(1, os.cpu_count() or 1)
