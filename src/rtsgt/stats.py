"""The chi-square test shared by the self-checks and the calibration's fit check.

A variance ratio (an observed mean of squared normalised errors) is 1 if the predicted
covariance is right; with ``dof`` independent unit-variance Gaussian terms it is distributed
as ``chi2_dof / dof``. :func:`ratio_interval` is where it falls 95 % of the time (or with
another probability), and :func:`ratio_verdict` names where a value lies against that interval.
"""

from __future__ import annotations

from scipy import stats

__all__ = ["VERDICTS", "failed_regimes", "ratio_interval", "ratio_verdict", "verdict_meaning"]

#: Inside the interval, below it (the covariance too large), above it (too small).
VERDICTS = ("consistent", "pessimistic", "optimistic")


def ratio_interval(dof: float, tail: float = 0.025) -> tuple[float, float]:
    """``(chi2_dof(tail), chi2_dof(1 - tail)) / dof``: by default the 95 % interval
    ``(chi2_dof(0.025), chi2_dof(0.975)) / dof``; ``dof`` may be a non-integer effective
    number of degrees of freedom."""
    return float(stats.chi2.ppf(tail, dof) / dof), float(stats.chi2.ppf(1.0 - tail, dof) / dof)


def ratio_verdict(value: float, interval: tuple[float, float]) -> str:
    """``"consistent"`` inside ``interval``, ``"pessimistic"`` below, ``"optimistic"`` above."""
    lo, hi = interval
    return VERDICTS[0] if lo <= value <= hi else (VERDICTS[1] if value < lo else VERDICTS[2])


def verdict_meaning(verdict: str) -> str:
    """What a failed verdict says about the predicted uncertainty, for a warning."""
    return ("smaller than the errors: the covariance is too small" if verdict == VERDICTS[2]
            else "larger than the errors: the covariance is too large")


def failed_regimes(check: dict, unit: str):
    """``(name, result)`` of a check's ``overall`` and each of its ``regimes`` whose verdict is
    not consistent (``name``: "the whole run" or "the <regime> <unit>"), in that order."""
    parts = (("the whole run", check["overall"]),
             *((f"the {k} {unit}", v) for k, v in check["regimes"].items()))
    return [(name, v) for name, v in parts if v["verdict"] in VERDICTS[1:]]
