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
    dict
        ``stations``: per station :meth:`~rtsgt.calibration.gcp.FitCheck.as_dict`
        (``markers``, ``dof``, ``variance_factor``, ``axis_factors_xyz``, ``interval_95``,
        ``verdict``; against the instrument model); ``added_shot_sigma_mm``: the variance
        components the calibration added to every shot (``horizontal``, ``vertical``;
        :func:`rtsgt.calibration.gcp.extra_shot_variance`).

    With ``warn``, one :class:`~rtsgt.errors.RtsgtWarning` per station whose variance factor
    is outside its 95 % interval, saying what the calibration added for it.
    """
    h, v = (1e3 * x for x in calibration.extra_shot_sigma_m)
    added = (f"the calibration covariance carries the difference: {h:.2f} mm horizontal and "
             f"{v:.2f} mm vertical added to every shot (variance components of the residuals)"
             if h or v else "the calibration covariance is too small by about that factor")
    stations = {s: c.as_dict() for s, c in calibration.fit_checks.items()}
    for s, c in stations.items():
        if warn and c["verdict"] in ("optimistic", "pessimistic"):
            lo, hi = c["interval_95"]
            x, y, z = c["axis_factors_xyz"]
            what = (f"disagree more than the instrument model predicts; {added}"
                    if c["verdict"] == "optimistic" else
                    "agree better than the instrument model predicts: the calibration "
                    "covariance is too large")
            warnings.warn(
                f"self-check, GCP fit of station {s}: variance factor {c['variance_factor']:.2f}"
                f" outside [{lo:.2f}, {hi:.2f}] (95 %, {c['dof']} degrees of freedom; per axis "
                f"x {x:.2f}, y {y:.2f}, z {z:.2f}): the GCP shots {what}",
                RtsgtWarning, stacklevel=2)
    return {"stations": stations, "added_shot_sigma_mm": {"horizontal": h, "vertical": v}}
