r"""The GP's effect on a prism's covariance, for a planned track (no measurements yet).

A run fits each prism's GP (:mod:`rtsgt.interpolation.gp`) to its measurements and queries
it between them; a plan has no measurements, so it takes the GP's posterior on a *stationary
uniform track*: measurements every ``h`` seconds (``1 / rate``) of a prism whose white noise
covariance ``R`` (3x3: the instrument and tilt sources, what a run gives the GP) does not
change from one measurement to the next, with the power spectral density ``Qc`` of the
white-noise-on-acceleration prior, queried at a time uniformly distributed between two
measurements (the query grid of a run falls anywhere between a station's measurements).

One axis
--------
For one axis with measurement variance ``lambda`` and PSD ``q``, scaling time by ``h`` and
position by ``sqrt(lambda)`` turns the problem into the one with ``h = 1``, ``lambda = 1``
and ``q = kappa``, with the dimensionless

.. math:: \kappa = q h^3 / \lambda ,

so the posterior variance is ``lambda g(kappa)``: ``g`` is the variance of the unit problem,
averaged over the query's position ``s`` in ``[0, 1)`` between two measurements (midpoint
rule, :data:`PHASES` points). :func:`gp_factor` tabulates ``g`` once, with
:func:`rtsgt.interpolation.gp.fit_track` itself on a synthetic track of :data:`TABLE_KNOTS`
measurements (the middle interval, far from both ends: the stationary value to 1e-7 for
``kappa >= 1e-4``), at :data:`LOG10_KAPPA`, and interpolates ``log g`` linearly in
``log kappa`` (0.125 decades apart: below 0.1 % error). Limits:

- smooth motion, ``kappa -> 0``: the continuum limit ``g = kappa^(1/4) / (2 sqrt 2)`` (the
  smoother averages ``~ kappa^(-1/4)`` measurements; the table meets it to 1e-7 at
  ``kappa = 1e-4``, below which it is used);
- rough motion, ``kappa -> infinity``: ``g ~ 0.00568 kappa``, the prior's own variance
  between two nearly exact measurements (``q h^3`` times a constant), grows without bound:
  above the table's end ``g`` is extended proportionally to ``kappa``.

At ``kappa = 100`` (2 mm of range noise, ``Qc = 0.006 m^2/s^3``, 2.5 Hz) ``g = 1.37``: the
GP no longer averages the noise away, and interpolating between measurements adds to it.

Three axes
----------
A prism's ``R`` is far from isotropic (the range and the two angles). In the eigenbasis
``R = V diag(lambda_k) V^T`` each direction ``v_k`` is a one-axis problem with
``q_k = v_k^T Qc v_k``, and

.. math:: \Sigma_{GP} = V \operatorname{diag}(\lambda_k\, g(q_k h^3 / \lambda_k)) V^T .

Exact for an isotropic ``Qc`` (the directions then decouple: tests/test_plan.py checks it
against a three-axis fit); for the per-axis ``Qc`` of a run (world x, y, z) it neglects the
coupling of the directions through ``Qc``'s anisotropy.

What it neglects: the ends of the track and its gaps (line-of-sight losses), a covariance
that changes along the track (it is taken where the prism is), and a ``Qc`` that changes with
the motion within a class (:mod:`rtsgt.interpolation.motion`).
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
    """``g(kappa)``: the GP's posterior variance over the measurement variance, averaged over
    the query's position between two measurements (module docstring).

    Parameters
    ----------
    kappa : array_like
        ``q h^3 / lambda`` (dimensionless), > 0.

    Returns
    -------
    ndarray, shape of ``kappa``
    """
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
    """The GP's posterior covariance of a prism on a stationary uniform track (module
    docstring, section Three axes).

    Parameters
    ----------
    white : array_like, shape (P, 3, 3)
        Covariance of one measurement as given to the GP (the white sources), m^2.
    qc : array_like, shape (3, 3) or (P, 3, 3)
        Power spectral density of the prior, m^2/s^3.
    interval_s : float or array_like, shape (P,)
        Time between two measurements, s.

    Returns
    -------
    ndarray, shape (P, 3, 3)
        m^2, averaged over the query's position between two measurements.
    """
    R = np.asarray(white, dtype=float)
    lam, V = np.linalg.eigh(0.5 * (R + np.swapaxes(R, -1, -2)))
    Q = np.broadcast_to(np.asarray(qc, dtype=float), R.shape)
    q = np.einsum("pak,pab,pbk->pk", V, Q, V)
    h = np.broadcast_to(np.asarray(interval_s, dtype=float), R.shape[:1])
    if np.any(~(lam > 0)) or np.any(~(q > 0)) or np.any(~(h > 0)):
        raise ValueError("Expected a positive definite covariance and Qc, and intervals > 0")
    var = lam * gp_factor(q * h[:, None] ** 3 / lam)
    return np.einsum("pak,pk,pbk->pab", V, var, V)
