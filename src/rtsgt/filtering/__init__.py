"""Filtering of tracked measurements (Vaidis et al. 2022): rate gates (module 1), intervals
where every prism is tracked (module 2); pose gates (module 4) live in :mod:`.gates`."""

from rtsgt.filtering.modules import (
    MODULE1_REASONS,
    MODULE2_REASONS,
    FilterParams,
    FilterReport,
    module1,
    module2,
)

__all__ = [
    "MODULE1_REASONS",
    "MODULE2_REASONS",
    "FilterParams",
    "FilterReport",
    "module1",
    "module2",
]
