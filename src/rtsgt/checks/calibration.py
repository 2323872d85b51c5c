"""Self-check of the extrinsic calibration: each station's GCP residuals against their
predicted covariance (:class:`rtsgt.calibration.gcp.FitCheck`: the a-posteriori variance
factor with its chi-square test, and per world axis)."""

from __future__ import annotations

import warnings
from typing import Any

from rtsgt.calibration import CalibrationResult
from rtsgt.errors import RtsgtWarning

__all__ = ["LEVELLING_FALSE_ALARM", "gcp_fit_check"]

#: False-alarm rate of the levelling test over a run's stations (Bonferroni).
LEVELLING_FALSE_ALARM = 0.05


def gcp_fit_check(calibration: CalibrationResult, *, warn: bool = True) -> dict[str, Any]:
    """The GCP fit check of every calibrated station, JSON-ready.

    Returns
    -------
    dict
        ``stations``: per station :meth:`~rtsgt.calibration.gcp.FitCheck.as_dict`
        (``markers``, ``dof``, ``variance_factor``, ``axis_factors_xyz``, ``interval_95``,
        ``verdict``; against the instrument model); ``added_shot_sigma_mm``: the variance
        components the calibration added to every shot (``horizontal``, ``vertical``;
        :func:`rtsgt.calibration.gcp.extra_shot_variance`); ``model``: the model of the
        stations' transforms (``"6dof"`` or ``"4dof"``); ``levelling``: per station the tilt
        against a levelled frame (:class:`~rtsgt.calibration.gcp.LevellingCheck`: ``tilt_urad``,
        ``sigma_urad``, ``chi2``, ``p_value``) and ``verdict``: ``levelled``, or ``tilted`` when
        ``p_value`` is below 5 % over the stations (Bonferroni).

    With ``warn``, one :class:`~rtsgt.errors.RtsgtWarning` per station whose variance factor
    is outside its 95 % interval, saying what the calibration added for it, and, under the
    4-DOF model, one per ``tilted`` station.
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
    levelling = {}
    for s, lv in calibration.levelling.items():
        tilted = lv.p_value < LEVELLING_FALSE_ALARM / len(calibration.levelling)
        levelling[s] = {**lv.as_dict(), "verdict": "tilted" if tilted else "levelled"}
        if warn and tilted and calibration.model == "4dof":
            x, y = levelling[s]["tilt_urad"]
            sx, sy = levelling[s]["sigma_urad"]
            warnings.warn(
                f"self-check, levelling of station {s}: its shots ask for a tilt of "
                f"({x:.1f} +- {sx:.1f}, {y:.1f} +- {sy:.1f}) microradians against the "
                f"reference (chi2 {lv.chi2:.1f}, 2 dof, p = {lv.p_value:.2g}): the 4-DOF "
                f"(levelled) calibration does not hold; use [calibration] model = \"6dof\"",
                RtsgtWarning, stacklevel=2)
    return {"model": calibration.model, "weighting": calibration.weighting, "stations": stations,
            "added_shot_sigma_mm": {"horizontal": h, "vertical": v}, "levelling": levelling}
