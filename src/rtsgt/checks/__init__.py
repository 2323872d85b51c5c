"""Self-checks of a run: what the data say about its uncertainty (Type A evaluations, GUM).

- :mod:`rtsgt.checks.distances`: the tracked inter-prism distances against the survey, overall
  and by regime (static, manoeuvring, cruising, far from a measurement);
- :mod:`rtsgt.checks.calibration`: each station's GCP residuals against their predicted
  covariance (the variance factor and its chi-square test); the dynamic calibration's
  distance residuals, and its agreement with the GCP calibration;
- :mod:`rtsgt.checks.block_cv`: block cross-validation of each prism track with the run's
  ``Qc`` (held-out windows of 1 s and 2 s), overall and by regime (standing, steady,
  accelerating; near and far into the gap);
- :mod:`rtsgt.checks.static`: the measurement noise on the run's static stretches (scatter
  and correlation time along and across the line of sight) against the instrument model;
- :mod:`rtsgt.checks.structure`: the structure of the inter-prism distance residuals, by
  regression: clock offsets that change over the run, and errors of the prisms that follow
  their orientation.
"""

from rtsgt.checks.block_cv import block_cv_check
from rtsgt.checks.calibration import dynamic_calibration_check, gcp_fit_check
from rtsgt.checks.distances import REGIMES, effective_sample_size, inter_prism_check
from rtsgt.checks.static import static_noise_check, static_stretches
from rtsgt.checks.structure import inter_prism_structure_check, run_structure_check

__all__ = ["REGIMES", "block_cv_check", "dynamic_calibration_check", "effective_sample_size",
           "gcp_fit_check",
           "inter_prism_check", "inter_prism_structure_check", "run_structure_check",
           "static_noise_check", "static_stretches"]
