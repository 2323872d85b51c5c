"""The chi-square test shared by the self-checks and the calibration's fit check.

A variance ratio (an observed mean of squared normalised errors) is 1 if the predicted
covariance is right; with ``dof`` independent unit-variance Gaussian terms it is distributed
as ``chi2_dof / dof``. :func:`ratio_interval` is where it falls 95 % of the time (or with
another probability), and :func:`ratio_verdict` names where a value lies against that interval;
:func:`integrated_autocorrelation_time` gives the effective sample size of a correlated series.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

__all__ = ["VERDICTS", "failed", "failed_regimes", "integrated_autocorrelation_time",
           "ratio_interval", "ratio_verdict", "verdict_meaning"]

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


def failed(parts) -> list[tuple[str, dict]]:
    """The ``(name, result)`` of ``parts`` whose verdict is pessimistic or optimistic (not
    consistent, and not without a verdict), in their order."""
    return [(name, v) for name, v in parts if v["verdict"] in VERDICTS[1:]]


def failed_regimes(check: dict, unit: str):
    """``(name, result)`` of a check's ``overall`` and each of its ``regimes`` whose verdict is
    not consistent (``name``: "the whole run" or "the <regime> <unit>"), in that order."""
    return failed((("the whole run", check["overall"]),
                   *((f"the {k} {unit}", v) for k, v in check["regimes"].items())))


def integrated_autocorrelation_time(x: ArrayLike) -> float:
    r"""Integrated autocorrelation time ``tau = 1 + 2 sum_{k>=1} rho_k`` of a series.

    The sum stops at the first lag whose sample autocorrelation is not positive (the initial
    positive sequence, Geyer 1992, in its simplest form). ``tau >= 1``; the effective number of
    independent samples of an average over N values is ``N / tau``.
    """
    x = np.asarray(x, dtype=float)
    n = x.size
    if n < 3:
        return 1.0
    x0 = x - x.mean()
    var = float(x0 @ x0)
    if var <= 0:
        return 1.0
    f = np.fft.rfft(x0, 2 * n)
    acf = np.fft.irfft(f * np.conj(f), 2 * n)[:n] / var
    nonpos = np.flatnonzero(acf[1:] <= 0)
    stop = int(nonpos[0]) + 1 if nonpos.size else n
    return max(1.0, 1.0 + 2.0 * float(np.sum(acf[1:stop])))
