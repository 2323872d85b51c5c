"""The progress callback of a run and the stopwatch of its stages (seconds per stage)."""

from __future__ import annotations

import time
from collections.abc import Callable

#: Called with the name of each stage as it starts (for progress displays).
Progress = Callable[[str], None]


def silent(stage: str) -> None:
    """A progress callback that says nothing."""


class Stopwatch:
    """Seconds per stage: :meth:`lap` records, under a stage's name, the time since the last
    lap (or since the start or :meth:`restart`), s, in :attr:`timings`."""

    def __init__(self, timings: dict[str, float] | None = None) -> None:
        self.timings: dict[str, float] = {} if timings is None else timings
        self.tick = time.perf_counter()

    def lap(self, name: str) -> None:
        """Record the time since the last lap under ``name``."""
        now = time.perf_counter()
        self.timings[name] = now - self.tick
        self.tick = now

    def restart(self) -> None:
        """Start the next lap now (the time since the last one counts nowhere)."""
        self.tick = time.perf_counter()
