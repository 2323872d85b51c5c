"""Self-check of the extrinsic calibration: each station's GCP residuals against their
predicted covariance (:class:`rtsgt.calibration.gcp.FitCheck`: the a-posteriori variance
factor with its chi-square test, and per world axis)."""

from __future__ import annotations

import warnings
from typing import Any

from rtsgt.calibration import CalibrationResult
from rtsgt.errors import RtsgtWarning

__all__ = ["gcp_fit_check"]


def gcp_fit_check(calibration: CalibrationResult, *, warn: bool = True) -> dict[str, Any]:
    """The GCP fit check of every calibrated station, JSON-ready.

    Returns
    -------
    dict station -> dict
        :meth:`~rtsgt.calibration.gcp.FitCheck.as_dict`: ``markers``, ``dof``,
        ``variance_factor``, ``axis_factors_xyz``, ``interval_95``, ``verdict``.

    With ``warn``, one :class:`~rtsgt.errors.RtsgtWarning` per station whose variance factor
    is outside its 95 % interval.
    """
    out = {s: c.as_dict() for s, c in calibration.fit_checks.items()}
    for s, c in out.items():
        if warn and c["verdict"] in ("optimistic", "pessimistic"):
            lo, hi = c["interval_95"]
            x, y, z = c["axis_factors_xyz"]
            what = ("disagree more than the instrument model predicts: the calibration "
                    "covariance is too small" if c["verdict"] == "optimistic" else
                    "agree better than the instrument model predicts: the calibration "
                    "covariance is too large")
            warnings.warn(
                f"self-check, GCP fit of station {s}: variance factor {c['variance_factor']:.2f}"
                f" outside [{lo:.2f}, {hi:.2f}] (95 %, {c['dof']} degrees of freedom; per axis "
                f"x {x:.2f}, y {y:.2f}, z {z:.2f}): the GCP shots {what}",
                RtsgtWarning, stacklevel=2)
    return out
