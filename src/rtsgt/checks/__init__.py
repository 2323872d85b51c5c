"""Self-checks of a run: what the data say about its uncertainty (Type A evaluations, GUM).

- :mod:`rtsgt.checks.distances`: the tracked inter-prism distances against the survey, overall
  and by regime (static, manoeuvring, cruising, far from a measurement).
"""

from rtsgt.checks.distances import REGIMES, effective_sample_size, inter_prism_check

__all__ = ["REGIMES", "effective_sample_size", "inter_prism_check"]
