"""Time-correlated measurement noise carried into the GP by inflating its white covariance.

Where the static-stretch check finds a component's noise correlated, its white covariance is
inflated by the independence factor ``k = (1 - f) + f (1 + rho) / (1 - rho)`` in the
measurement's sight frame; what that adds is the source ``correlated_noise``. Derivation and
limits: docs/noise-model.md#time-correlated-noise.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.measurement.polar import SIGHT_COMPONENTS, sight_frames
from rtsgt.noise.sources import CORRELATED_NOISE_SOURCE, WHITE_NOISE_SOURCES
from rtsgt.types import PrismTrack

__all__ = ["correlated_noise_plan", "independence_factor", "inflate_tracks"]

#: The correlation verdict of the static-stretch check for which the noise is inflated.
CORRELATED = "optimistic"


def independence_factor(f: ArrayLike, tau: ArrayLike, dt: ArrayLike) -> np.ndarray:
    """``k = (1 - f) + f (1 + rho) / (1 - rho)``, ``rho = exp(-dt / tau)`` (>= 1): the variance
    of a long average of white plus Gauss-Markov noise (correlated share ``f`` in [0, 1),
    correlation time ``tau`` > 0, s) over that of white noise, measurements every ``dt`` s."""
    f = np.asarray(f, dtype=float)
    x = np.asarray(dt, dtype=float) / np.asarray(tau, dtype=float)
    return (1.0 - f) + f * (1.0 + np.exp(-x)) / -np.expm1(-x)


def correlated_noise_plan(static_check: Mapping[str, Any], tracks: Mapping[str, PrismTrack],
                          *, apply: bool) -> dict[str, Any]:
    """Which prisms and components to inflate, by how much (JSON-ready), from the run's
    static-stretch check (:func:`rtsgt.checks.static_noise_check`) and the ``tracks`` (their
    median interval is ``dt``); ``apply`` False gives the factors without applying them.

    Returns ``mode`` ("inflate" or "ignore"), ``applied``, and per prism the
    ``median_interval_s`` and per component the check's ``verdict``, ``correlated_fraction``,
    ``correlation_time_s``, ``rho``, ``factor`` (1 where not correlated) and ``applied``;
    ``note`` where no prism has a result.
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
    """The world-frame ``tracks`` with the white covariance of the ``plan``'s components
    inflated in the sight frame from their ``stations`` (world, m): the added ``A W A - W`` in
    the total and as the source :data:`~rtsgt.noise.sources.CORRELATED_NOISE_SOURCE`; tracks
    left alone are the same objects.
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
