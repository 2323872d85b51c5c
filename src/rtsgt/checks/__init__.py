"""Self-checks of a run: what the data say about its uncertainty (Type A evaluations, GUM):
the inter-prism distances (:mod:`~rtsgt.checks.distances`) and their structure
(:mod:`~rtsgt.checks.structure`), the GCP and dynamic calibrations
(:mod:`~rtsgt.checks.calibration`), block cross-validation of the tracks
(:mod:`~rtsgt.checks.block_cv`), the static stretches' noise (:mod:`~rtsgt.checks.static`) and
the run's verdict (:mod:`~rtsgt.checks.verdict`). docs/self-checks.md.
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
