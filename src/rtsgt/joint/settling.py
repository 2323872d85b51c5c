"""The stations' set-ups settling during the deployment, as global parameters of the joint
engine: each station's height and yaw change since its calibration, piecewise linear with
knots every :data:`rtsgt.clocks.KNOT_SPACING_S` (the clocks' grid), with a prior of a random
walk plus a drift from its calibration on: docs/joint.md#settling-tripods.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.clocks import KNOT_SPACING_S
from rtsgt.joint.clock import clock_knots, knot_intervals
from rtsgt.measurement.instruments import ARCSEC

#: The settling's kinds, in the order of every (..., 2) axis here: the station's height (m,
#: along the world's vertical) and yaw (rad, about it), columns 2 and 5 of a station's
#: ``(dt, dtheta)`` (:func:`rtsgt.joint.measurements.predict`'s ``H_station``).
KINDS = ("height", "yaw")
#: Their columns among a station's ``(dt, dtheta)``.
KIND_COLUMNS = (2, 5)
#: Prior size of a set-up's change an hour after its calibration, per kind, as the sigmas of
#: two processes from 0 at the calibration: a random walk (``HOUR_WALK_SIGMA``: a tripod's
#: legs settle fastest right after set-up) and a drift (``HOUR_DRIFT_SIGMA``, a rate random
#: walk from rest: the sun's heating twists it steadily); a tripod sinks by tenths of a
#: millimetre to a millimetre and twists by arc seconds within an hour
#: (docs/joint.md#settling-tripods).
HOUR_WALK_SIGMA = (1.0e-3, 5.0 * ARCSEC)
HOUR_DRIFT_SIGMA = (1.0e-3, 5.0 * ARCSEC)
#: Sigma of the set-up at its calibration (the calibration's own covariance carries it; a
#: jitter keeping the prior's covariance invertible), m and rad.
ANCHOR_SIGMA = (1e-7, 1e-9)
HOUR_S = 3600.0


@dataclass(frozen=True)
class SettleModel:
    """``knots`` (J,) s; ``info`` (S, 2, J, J) the prior information of each station's knots
    per kind (:data:`KINDS`; m^-2, rad^-2); per measurement ``j`` (M,) its interval's left
    knot and ``u`` (M,) its position in it (0-1). The states, (S, 2, J), are the globals
    ``base + (2 s + kind) J + j``."""

    knots: np.ndarray
    info: np.ndarray
    j: np.ndarray
    u: np.ndarray

    @property
    def n_stations(self) -> int:
        return self.info.shape[0]

    @property
    def size(self) -> int:
        return self.n_stations * 2 * self.knots.size

    def at(self, states: np.ndarray, station: np.ndarray) -> np.ndarray:
        """Each measurement's settling (M, 2) (height m, yaw rad) from the knots' ``states``
        (S, 2, J) and its ``station`` (M,)."""
        a = states[station, :, self.j]
        b = states[station, :, self.j + 1]
        return (1.0 - self.u)[:, None] * a + self.u[:, None] * b

    def columns(self, station: np.ndarray, base: int) -> np.ndarray:
        """Each measurement's four global columns (M, 4): height at its interval's two knots,
        then yaw at them; ``base`` the first settling column."""
        J = self.knots.size
        first = base + (2 * station[:, None] + np.arange(2)[None, :]) * J + self.j[:, None]
        return np.stack([first[:, 0], first[:, 0] + 1, first[:, 1], first[:, 1] + 1], axis=1)


def settle_prior_info(knots: np.ndarray, walk_sigma: float, drift_sigma: float,
                      calibrated_at: float, anchor_sigma: float) -> np.ndarray:
    """Information (J, J) of one station's knots ``knots`` (J,) s of one kind: the inverse of
    the covariance of a random walk (``q_w = walk_sigma^2 / 1 h``, ``q_w min(a, b)``) plus an
    integrated one from rest (``q_d = 3 drift_sigma^2 / (1 h)^3``,
    ``q_d min^2 (3 max - min) / 6``), both 0 at ``calibrated_at`` s (at or before the first
    knot; ``a``, ``b`` the knots' times since it), plus ``anchor_sigma^2`` on the diagonal."""
    tau = np.maximum(np.asarray(knots, dtype=float) - calibrated_at, 0.0)
    lo = np.minimum.outer(tau, tau)
    hi = np.maximum.outer(tau, tau)
    cov = (walk_sigma**2 / HOUR_S * lo + 3.0 * drift_sigma**2 / HOUR_S**3
           * lo**2 * (3.0 * hi - lo) / 6.0 + anchor_sigma**2 * np.eye(tau.size))
    info = np.linalg.inv(cov)
    return 0.5 * (info + info.T)


def settle_model(t: np.ndarray, calibrated_at: np.ndarray, spacing: float = KNOT_SPACING_S,
                 scale: tuple[float, float] = (1.0, 1.0)) -> SettleModel:
    """The settling states of each station for measurements at times ``t`` (M,) s;
    ``calibrated_at`` (S,) s each station's calibration time (at most the first measurement's;
    later ones are taken as at it); ``scale`` multiplies each kind's sigmas."""
    knots = clock_knots(float(t.min()), float(t.max()), spacing)
    cal = np.minimum(np.asarray(calibrated_at, dtype=float), knots[0])
    info = np.stack([[settle_prior_info(knots, HOUR_WALK_SIGMA[k] * scale[k],
                                        HOUR_DRIFT_SIGMA[k] * scale[k], c, ANCHOR_SIGMA[k])
                      for k in range(2)] for c in cal])
    return SettleModel(knots, info, *knot_intervals(knots, t))


__all__ = ["HOUR_DRIFT_SIGMA", "HOUR_WALK_SIGMA", "KINDS", "KIND_COLUMNS", "SettleModel",
           "settle_model", "settle_prior_info"]
