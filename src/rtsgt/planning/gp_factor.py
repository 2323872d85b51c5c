r"""The GP's effect on a prism's covariance, for a planned track (no measurements yet).

The GP's posterior on a stationary uniform track (measurements every ``h`` s of constant
white covariance ``R``, PSD ``Qc``, the query uniform between two measurements) is, per
eigen-direction of ``R``, ``lambda g(kappa)`` with ``kappa = q h^3 / lambda``; ``g`` is
tabulated once with :func:`rtsgt.interpolation.gp.fit_track` and extended by its smooth and
rough limits. Derivation, limits and what it neglects: docs/planning.md#the-gp-and-qc.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.interpolation.gp import fit_track

__all__ = ["LOG10_KAPPA", "PHASES", "TABLE_KNOTS", "gp_factor", "gp_posterior_covariance"]

#: ``log10 kappa`` of the table's nodes.
LOG10_KAPPA = np.arange(-4.0, 10.0 + 1e-9, 0.125)
LOG10_KAPPA.setflags(write=False)
#: Measurements of the synthetic track the table is computed on.
TABLE_KNOTS = 401
#: Query positions between two measurements averaged (midpoint rule).
PHASES = 16
#: ``g`` in the continuum limit is ``kappa^(1/4) * SMOOTH_LIMIT``.
SMOOTH_LIMIT = 1.0 / (2.0 * np.sqrt(2.0))


@lru_cache(maxsize=1)
def _log_table() -> np.ndarray:
    """``log g`` at :data:`LOG10_KAPPA` (computed once per process, ~0.3 s)."""
    n = TABLE_KNOTS
    t = np.arange(n, dtype=float)
    y = np.zeros((n, 3))
    cov = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    tau = n // 2 + (np.arange(PHASES) + 0.5) / PHASES
    out = np.empty(LOG10_KAPPA.size)
    for i, lk in enumerate(LOG10_KAPPA):  # the table's nodes, once
        gp = fit_track((t, y, cov), qc=10.0 ** lk, max_gap_s=2.0)
        out[i] = np.log(gp.query(tau).position_cov[:, 0, 0].mean())
    out.setflags(write=False)
    return out


def gp_factor(kappa: ArrayLike) -> np.ndarray:
    """``g(kappa)`` (shape of ``kappa``): the GP's posterior variance over the measurement variance,
    averaged over the query's position between two measurements, for ``kappa = q h^3 / lambda``
    > 0 (docs/planning.md#the-gp-and-qc)."""
    k = np.asarray(kappa, dtype=float)
    if np.any(~(k > 0)):
        raise ValueError("Expected kappa > 0")
    table = _log_table()
    lk = np.log10(k)
    top = LOG10_KAPPA[-1]
    log_g = np.interp(np.minimum(lk, top), LOG10_KAPPA, table)
    log_g = log_g + np.log(10.0) * np.maximum(lk - top, 0.0)  # g proportional to kappa
    smooth = np.log(SMOOTH_LIMIT) + 0.25 * np.log(np.where(lk < LOG10_KAPPA[0], k, 1.0))
    return np.exp(np.where(lk < LOG10_KAPPA[0], smooth, log_g))


def gp_posterior_covariance(white: ArrayLike, qc: ArrayLike, interval_s: ArrayLike) -> np.ndarray:
    """The GP's posterior covariance (P, 3, 3), m^2, of a prism on a stationary uniform track,
    averaged over the query's position: per eigen-direction of the ``white`` covariance (P, 3, 3),
    m^2, the prior ``qc`` (3, 3) or (P, 3, 3), m^2/s^3, and ``interval_s`` (P,) between
    measurements, s."""
    R = np.asarray(white, dtype=float)
    lam, V = np.linalg.eigh(0.5 * (R + np.swapaxes(R, -1, -2)))
    Q = np.broadcast_to(np.asarray(qc, dtype=float), R.shape)
    q = np.einsum("pak,pab,pbk->pk", V, Q, V)
    h = np.broadcast_to(np.asarray(interval_s, dtype=float), R.shape[:1])
    if np.any(~(lam > 0)) or np.any(~(q > 0)) or np.any(~(h > 0)):
        raise ValueError("Expected a positive definite covariance and Qc, and intervals > 0")
    var = lam * gp_factor(q * h[:, None] ** 3 / lam)
    return np.einsum("pak,pk,pbk->pab", V, var, V)
