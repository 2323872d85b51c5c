"""The stations' set-ups settling during the deployment in the joint engine: each station's
height and yaw change since its calibration, a level and its rate at every knot
(:mod:`rtsgt.joint.slow`), from rest at its calibration: a random walk plus a drift
(docs/joint.md#settling-tripods).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.clocks import level_rate_noise
from rtsgt.joint.slow import LevelRate
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
    """``n_stations`` stations' settling, per station and kind (:data:`KINDS`) one process of
    ``prior`` (:class:`rtsgt.joint.slow.LevelRate`; process ``2 s + kind``, m and rad). A
    knot's settling states (``4 S``) are, per station and kind, the change (level) and its
    rate."""

    n_stations: int
    prior: LevelRate

    @property
    def size(self) -> int:
        """States per knot."""
        return self.prior.size

    def at(self, z: np.ndarray, knot: np.ndarray, station: np.ndarray, tau: np.ndarray
           ) -> np.ndarray:
        """Each measurement's settling (M, 2) (height m, yaw rad), ``level + tau rate`` of
        its knot ``knot`` (M,) at ``tau`` (M,) s from it, its station ``station`` (M,), from
        the knots' states ``z`` (K, 4 S)."""
        c = 4 * station[:, None] + 2 * np.arange(2)[None, :]  # (M, 2) the levels' columns
        k = knot[:, None]
        return z[k, c] + tau[:, None] * z[k, c + 1]

    def jacobian(self, station: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """``d settling / d z_k`` (M, 2, 4 S) of :meth:`at`."""
        M = station.size
        J = np.zeros((M, 2, self.size))
        m = np.arange(M)
        for kind in range(2):
            c = 4 * station + 2 * kind
            J[m, kind, c] = 1.0
            J[m, kind, c + 1] = tau
        return J


def settle_start(walk_sigma: float, drift_sigma: float, elapsed: float,
                 anchor_sigma: float) -> np.ndarray:
    """Covariance (2, 2) of one kind's ``(change, rate)`` ``elapsed`` s after its calibration
    (from rest, zero change, there): a random walk of intensity ``walk_sigma^2 / 1 h`` and an
    integrated one of ``3 drift_sigma^2 / (1 h)^3`` (:func:`rtsgt.clocks.level_rate_noise`)
    plus ``anchor_sigma^2`` on the change and ``(anchor_sigma / 1 h)^2`` on its rate."""
    Q = level_rate_noise(np.asarray(max(elapsed, 0.0)), walk_sigma**2 / HOUR_S,
                         3.0 * drift_sigma**2 / HOUR_S**3)
    return Q + np.diag([anchor_sigma**2, (anchor_sigma / HOUR_S) ** 2])


def settle_model(t0: float, calibrated_at: np.ndarray,
                 scale: tuple[float, float] = (1.0, 1.0)) -> SettleModel:
    """The settling states of each station from the first knot's time ``t0`` s on;
    ``calibrated_at`` (S,) s each station's calibration time (at most ``t0``; later ones are
    taken as at it); ``scale`` multiplies each kind's sigmas."""
    cal = np.minimum(np.asarray(calibrated_at, dtype=float), t0)
    walk = np.array([HOUR_WALK_SIGMA[k] * scale[k] for k in range(2)])
    drift = np.array([HOUR_DRIFT_SIGMA[k] * scale[k] for k in range(2)])
    start = np.stack([settle_start(walk[k], drift[k], t0 - c, ANCHOR_SIGMA[k])
                      for c in cal for k in range(2)])
    n = cal.size
    prior = LevelRate(np.tile(walk**2 / HOUR_S, n), np.tile(3.0 * drift**2 / HOUR_S**3, n),
                      start)
    return SettleModel(n, prior)


__all__ = ["HOUR_DRIFT_SIGMA", "HOUR_WALK_SIGMA", "KINDS", "KIND_COLUMNS", "SettleModel",
           "settle_model", "settle_start"]
