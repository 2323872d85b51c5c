"""Self-checks of a run: what the data say about its uncertainty (Type A evaluations, GUM).

- :mod:`rtsgt.checks.distances`: the tracked inter-prism distances against the survey, overall
  and by regime (static, manoeuvring, cruising, far from a measurement);
- :mod:`rtsgt.checks.calibration`: each station's GCP residuals against their predicted
  covariance (the variance factor and its chi-square test);
- :mod:`rtsgt.checks.structure`: the structure of the inter-prism distance residuals, by
  regression: clock offsets that change over the run, and errors of the prisms that follow
  their orientation.
"""

from rtsgt.checks.calibration import gcp_fit_check
from rtsgt.checks.distances import REGIMES, effective_sample_size, inter_prism_check
from rtsgt.checks.structure import inter_prism_structure_check, run_structure_check

__all__ = ["REGIMES", "effective_sample_size", "gcp_fit_check", "inter_prism_check",
           "inter_prism_structure_check", "run_structure_check"]
