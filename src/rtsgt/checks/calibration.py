"""Self-checks of the extrinsic calibration: :func:`gcp_fit_check` (each station's GCP
residuals against their predicted covariance) and :func:`dynamic_calibration_check` (the
dynamic or joint fit's residuals, its clock offsets, and a dynamic fit's chi-square agreement
with the GCP calibration per station). Method: docs/calibration.md#self-checks.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from scipy.stats import chi2 as chi2_dist

from rtsgt.calibration import CalibrationResult
from rtsgt.errors import RtsgtWarning
from rtsgt.geometry.transform import perturbation

__all__ = ["AGREEMENT_FALSE_ALARM", "LEVELLING_FALSE_ALARM", "dynamic_calibration_check",
           "gcp_fit_check"]

#: False-alarm rate of the levelling test over a run's stations (Bonferroni).
LEVELLING_FALSE_ALARM = 0.05
#: False-alarm rate of the dynamic-against-GCP agreement test over a run's stations.
AGREEMENT_FALSE_ALARM = 0.05
_AXES = ("x", "y", "z", "rx", "ry", "rz")
#: The components compared under each model (x, y, z, rx, ry, rz).
_COMPARED = {"6dof": [0, 1, 2, 3, 4, 5], "4dof": [0, 1, 2, 5]}


def gcp_fit_check(calibration: CalibrationResult, *, warn: bool = True) -> dict[str, Any]:
    """The GCP fit check of every calibrated station, JSON-ready: ``stations`` (per station
    :meth:`~rtsgt.calibration.gcp.FitCheck.as_dict`), ``added_shot_sigma_mm`` (the variance
    components added to every shot), ``model``, ``weighting`` and ``levelling`` (per station the
    tilt against a levelled frame; ``tilted`` below 5 % over the stations, Bonferroni). ``warn``:
    one warning per station whose variance factor is outside its interval, and under the 4-DOF
    model one per tilted station."""
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


def calibration_agreement(a: CalibrationResult, b: CalibrationResult) -> dict[str, Any]:
    """Per station, the difference of two calibrations fitted to independent data, in units of
    their combined covariance (module docstring), JSON-ready: ``difference_mm_mrad`` (x, y, z in
    mm, rx, ry, rz in mrad; ``b`` relative to ``a``), ``sigma_mm_mrad`` (the combined standard
    deviations), ``z`` (their ratio, the compared components), ``chi2``, ``dof``, ``p_value``,
    ``verdict`` (``agree`` or ``disagree``)."""
    idx = _COMPARED[a.model]
    out = {}
    common = [s for s in a.transforms if s != a.reference_station and s in b.transforms]
    for s in common:
        Ta, Tb = a.transforms[s], b.transforms[s]
        if Ta.covariance is None or Tb.covariance is None:
            continue
        e = perturbation(Ta.rotation, Ta.translation, Tb.rotation, Tb.translation)
        C = Ta.covariance + Tb.covariance
        sub = C[np.ix_(idx, idx)]
        c2 = float(e[idx] @ np.linalg.solve(sub, e[idx]))
        p = float(chi2_dist.sf(c2, len(idx)))
        sig = np.sqrt(np.diag(C))
        out[s] = {"difference_mm_mrad": (1e3 * e).tolist(),
                  "sigma_mm_mrad": (1e3 * sig).tolist(),
                  "z": {_AXES[k]: float(e[k] / sig[k]) for k in idx},
                  "chi2": c2, "dof": len(idx), "p_value": p,
                  "verdict": "disagree" if p < AGREEMENT_FALSE_ALARM / max(len(common), 1)
                  else "agree"}
    return out


def dynamic_calibration_check(calibration: CalibrationResult,
                              gcp: CalibrationResult | None = None, *,
                              warn: bool = True) -> dict[str, Any]:
    """The dynamic (or joint) calibration's self-check, JSON-ready:
    :meth:`rtsgt.calibration.dynamic.DynamicFit.as_dict`, the ``model`` and, for a dynamic
    calibration with ``gcp``, ``gcp_agreement`` (:func:`calibration_agreement`). ``warn``: one
    warning when the residuals are larger than predicted (``optimistic``) and one per station
    that disagrees with the GCPs."""
    fit = calibration.dynamic
    out = {"model": calibration.model, **fit.as_dict()}
    if warn and fit.verdict == "optimistic":
        lo, hi = fit.interval_95
        warnings.warn(
            f"self-check, {fit.method} calibration: variance factor of the inter-prism "
            f"distances {fit.variance_factor:.2f} outside [{lo:.2f}, {hi:.2f}] (95 %, "
            f"{fit.dof:.0f} effective degrees of freedom): the tracked distances disagree with "
            "the survey more than the tracks' covariance predicts; the calibration covariance "
            "is too small by about that factor", RtsgtWarning, stacklevel=2)
    if gcp is not None and fit.method == "dynamic":
        agree = calibration_agreement(gcp, calibration)
        out["gcp_agreement"] = agree
        for s, v in agree.items():
            if warn and v["verdict"] == "disagree":
                axis, z = max(v["z"].items(), key=lambda kv: abs(kv[1]))
                k = _AXES.index(axis)
                size = f"{v['difference_mm_mrad'][k]:+.1f} {'mm' if k < 3 else 'mrad'}"
                warnings.warn(
                    f"self-check, calibration of station {s}: the dynamic and the GCP "
                    f"calibrations differ by chi2 {v['chi2']:.1f} ({v['dof']} dof, "
                    f"p = {v['p_value']:.2g}; largest along {axis}: the dynamic {size} from "
                    f"the GCPs', {z:+.1f} combined sigma): one of them, or its covariance, is "
                    "wrong",
                    RtsgtWarning, stacklevel=2)
    return out
