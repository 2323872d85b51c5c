r"""Time-correlated measurement noise carried into the GP by inflating its white covariance.

The GP of a prism (:mod:`rtsgt.interpolation.gp`) takes its measurements as independent: its
posterior variance falls as ``1 / n`` with the ``n`` measurements it averages. Where the
static-stretch check (:mod:`rtsgt.checks.static`) finds that a component of a prism's noise
wanders (its lag-one correlation ``optimistic``), that is not true, and the run inflates the
white covariance of that component by the factor that makes ``n`` independent measurements
average like ``n`` correlated ones: the loss of independent samples.

The factor
----------
The check models the noise of one component, in units of its predicted white sigma, as white
plus a first-order Gauss-Markov process: ``cov(z_i, z_j) = v ((1 - f) delta_ij + f rho^|i - j|)``
for measurements at a regular interval ``dt``, with ``rho = exp(-dt / tau)`` (``f``: the
correlated share of the variance, ``tau``: the correlation time, both estimated on the run's
own static stretches). The mean of ``n`` consecutive measurements has the variance

.. code-block:: text

    var(mean_n) = v / n ((1 - f) + f g_n),   g_n = 1 + 2 sum_{l=1}^{n-1} (1 - l/n) rho^l
                                                  = (1 + rho) / (1 - rho)
                                                    - 2 rho (1 - rho^n) / (n (1 - rho)^2)

and for a long average (``n (1 - rho) >> 1``)

.. code-block:: text

    var(mean_n) -> k v / n,   k = (1 - f) + f (1 + rho) / (1 - rho)

(:func:`independence_factor`): ``n`` correlated measurements average like ``n / k``
independent ones (the effective number of independent samples). Giving the GP the white
covariance ``k C`` along that component makes its ``1 / n`` right for a long average.

Each measurement is inflated in its own frame, the frame the check splits it in
(:func:`rtsgt.measurement.polar.sight_frames`: the station's line of sight ``e_range`` and the
horizontal and vertical directions across it, ``E`` the 3x3 matrix of these rows), one factor
``k_c`` per component:

.. code-block:: text

    C' = A C A,   A = E^T S E,   S = diag(sqrt(k_range), sqrt(k_horizontal), sqrt(k_vertical))

``A`` is symmetric and positive definite, so ``C'`` is positive definite with ``C``; a
covariance diagonal in the measurement's frame (the instrument's, to first order) has its
variance along ``e_c`` multiplied by ``k_c`` exactly. ``C`` is the white covariance, the sum
``W`` of the sources ``instrument`` and ``tilt`` of
:attr:`~rtsgt.types.PrismTrack.cov_by_source`. Those stay as the noise model gives them (the
per-source analysis compares them with the paper); what the inflation adds, ``A W A - W``, is
a source of its own, ``correlated_noise``, which the GP takes with the white sources
(:data:`rtsgt.interpolation.prisms.WHITE_SOURCES`), and is added to the total covariance, so
that the GP is given ``A W A`` whether it takes the white sources (``gp_noise = "white"``) or
the total (``gp_noise = "all"``: only its white part changes). That source is positive
semi-definite where ``W`` is diagonal in the measurement's frame; otherwise (a Monte Carlo
covariance, the tilt) it may have small negative eigenvalues, and only its sum with ``W`` is a
covariance.

Limits
------
- Exact for a long GP window (a standing robot, a smooth motion: many measurements per
  correlation time averaged), conservative for a short one: ``g_n < (1 + rho) / (1 - rho)``,
  and a GP that follows a quick motion averages few measurements (one: the right factor is
  1). The covariance of poses in motion is therefore overstated by up to ``sqrt(k)`` along an
  inflated component; the other way round, carrying the correlation exactly for any
  averaging needs a state per correlated channel in the GP (state augmentation).
- The *level* of the noise is not changed: the check's variance ratio (the scatter on the
  static stretches against the instrument model) is a Type A evaluation of a few tens of
  seconds against the datasheet's Type B one, and the run keeps the model's; only the
  correlation structure (``f``, ``tau``) is taken from the data.
- ``f`` is overstated on stretches of a few tens of samples (docs/self-checks.md: 0.64 for
  0.5), which makes ``k`` larger; ``tau`` is bounded by the longest block of the check's fit
  (64 measurements), which bounds ``k`` (at 0.4 s per measurement, ``k <= 128``).
- The correlation is measured while the robot stands and assumed the same while it moves; a
  component without a verdict (fewer than 20 samples on the stretches, no stretch) or without
  correlation is left alone. The interval ``dt`` is the prism's median measurement interval.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.measurement.polar import SIGHT_COMPONENTS, sight_frames
from rtsgt.types import CORRELATED_NOISE_SOURCE, WHITE_NOISE_SOURCES, PrismTrack

__all__ = ["correlated_noise_plan", "independence_factor", "inflate_tracks"]

#: The correlation verdict of the static-stretch check for which the noise is inflated.
CORRELATED = "optimistic"


def independence_factor(f: ArrayLike, tau: ArrayLike, dt: ArrayLike) -> np.ndarray:
    """The variance of a long average of white plus Gauss-Markov noise over that of white
    noise of the same variance (module docstring).

    Parameters
    ----------
    f : array_like
        Correlated share of the variance, in [0, 1).
    tau : array_like
        Correlation time, s (> 0).
    dt : array_like
        Interval between measurements, s (> 0).

    Returns
    -------
    ndarray
        ``k = (1 - f) + f (1 + rho) / (1 - rho)``, ``rho = exp(-dt / tau)``: at least 1.
    """
    f = np.asarray(f, dtype=float)
    x = np.asarray(dt, dtype=float) / np.asarray(tau, dtype=float)
    return (1.0 - f) + f * (1.0 + np.exp(-x)) / -np.expm1(-x)


def correlated_noise_plan(static_check: Mapping[str, Any], tracks: Mapping[str, PrismTrack],
                          *, apply: bool) -> dict[str, Any]:
    """Which prisms and components to inflate, by how much (JSON-ready).

    Parameters
    ----------
    static_check : mapping
        The static-stretch check of the run (:func:`rtsgt.checks.static_noise_check`).
    tracks : mapping str -> PrismTrack
        The tracks to be inflated (their median measurement interval is ``dt``).
    apply : bool
        Whether the run inflates (``correlated_noise = "inflate"``); with False the factors
        are given for comparison and nothing is applied.

    Returns
    -------
    dict
        ``mode`` (``"inflate"`` or ``"ignore"``), ``applied`` (any component inflated),
        ``prisms``: per prism the check has, ``median_interval_s`` and per component
        ``verdict`` (the check's correlation verdict), ``correlated_fraction``,
        ``correlation_time_s``, ``rho``, ``factor`` (1 where not correlated) and
        ``applied``; ``note`` where no prism has a result.
    """
    out: dict[str, Any] = {"mode": "inflate" if apply else "ignore", "applied": False,
                           "prisms": {}}
    for pid, entry in static_check.get("prisms", {}).items():
        if pid not in tracks or len(tracks[pid]) < 2:
            continue
        dt = float(np.median(np.diff(tracks[pid].t)))
        prism: dict[str, Any] = {"median_interval_s": dt}
        for name in SIGHT_COMPONENTS:
            co = entry[name]["correlation"]
            f, tau = co.get("correlated_fraction"), co.get("correlation_time_s")
            found = bool(co.get("verdict") == CORRELATED and tau is not None and f)
            rho = float(np.exp(-dt / tau)) if found else None
            k = float(independence_factor(f, tau, dt)) if found else 1.0
            prism[name] = {"verdict": co.get("verdict"), "correlated_fraction": f,
                           "correlation_time_s": tau, "rho": rho, "factor": k,
                           "applied": bool(apply and found and k > 1.0)}
            out["applied"] |= prism[name]["applied"]
        out["prisms"][pid] = prism
    if not out["prisms"]:
        out["note"] = static_check.get("note", "no prism with a static-stretch result")
    return out


def inflate_tracks(tracks: Mapping[str, PrismTrack], stations: Mapping[str, ArrayLike],
                   plan: Mapping[str, Any]) -> dict[str, PrismTrack]:
    """The tracks with the white covariance of the planned components inflated (module
    docstring).

    Parameters
    ----------
    tracks : mapping str -> PrismTrack
        World-frame tracks with their station and per-source covariances.
    stations : mapping str -> array_like (3,)
        Station positions (world frame), m.
    plan : mapping
        :func:`correlated_noise_plan`.

    Returns
    -------
    dict str -> PrismTrack
        The same tracks (the same objects where nothing is applied); the others with the
        covariance the inflation adds to their white sources, ``A W A - W``, as the source
        ``correlated_noise`` (:data:`~rtsgt.types.CORRELATED_NOISE_SOURCE`,
        given to the GP with the white sources) and in the total covariance.
    """
    out = dict(tracks)
    for pid, prism in plan.get("prisms", {}).items():
        scale = np.sqrt([prism[c]["factor"] if prism[c]["applied"] else 1.0
                         for c in SIGHT_COMPONENTS])
        if pid not in tracks or not np.any(scale > 1.0):
            continue
        tr = tracks[pid]
        E = sight_frames(tr.xyz, np.asarray(stations[tr.station], dtype=float))
        A = np.einsum("nci,c,ncj->nij", E, scale, E)
        W = np.sum([tr.cov_by_source[s] for s in WHITE_NOISE_SOURCES
                    if s in tr.cov_by_source],
                   axis=0)
        added = A @ W @ A - W
        added = 0.5 * (added + np.swapaxes(added, 1, 2))
        by_source = dict(tr.cov_by_source)
        by_source[CORRELATED_NOISE_SOURCE] = by_source.get(CORRELATED_NOISE_SOURCE, 0.0) + added
        out[pid] = PrismTrack(tr.t, tr.xyz, tr.cov + added, by_source, tr.prism, tr.frame,
                              tr.station, tr.range_m)
    return out
