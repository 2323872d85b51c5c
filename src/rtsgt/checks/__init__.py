"""Self-checks of a run: what the data say about its uncertainty (Type A evaluations, GUM).

- :mod:`rtsgt.checks.distances`: the tracked inter-prism distances against the survey, overall
  and by regime (static, manoeuvring, cruising, far from a measurement);
- :mod:`rtsgt.checks.calibration`: each station's GCP residuals against their predicted
  covariance (the variance factor and its chi-square test);
- :mod:`rtsgt.checks.block_cv`: block cross-validation of each prism track with the run's
  ``Qc`` (held-out windows of 1 s and 2 s), overall and by regime (standing, steady,
  accelerating; near and far into the gap);
- :mod:`rtsgt.checks.static`: the measurement noise on the run's static stretches (scatter
  and correlation time along and across the line of sight) against the instrument model.
"""

from rtsgt.checks.block_cv import block_cv_check
from rtsgt.checks.calibration import gcp_fit_check
from rtsgt.checks.distances import REGIMES, effective_sample_size, inter_prism_check
from rtsgt.checks.static import static_noise_check, static_stretches

__all__ = ["REGIMES", "block_cv_check", "effective_sample_size", "gcp_fit_check",
           "inter_prism_check", "static_noise_check", "static_stretches"]
