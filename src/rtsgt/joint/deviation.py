"""The 360-degree prisms' deviation with the viewing angle, as global parameters of the joint
engine: per prism, low harmonics of the azimuth (in the body frame) under which its station
sees it, in range, across the line of sight and vertically; the survey-free prior of a few
millimetres a 360-degree prism's makers state: docs/joint.md#prism-deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Harmonics (per turn of the viewing azimuth) estimated: a six-faced 360-degree prism's
#: pattern repeats with each face (6, its second harmonic 12) and, where faces tilted up and
#: down alternate, with each pair of faces (3).
ORDERS = (3, 6, 12)
#: Components of the deviation, in the order of every component axis here: along the line of
#: sight (the distance, m, positive: longer), across it horizontally (positive: towards a
#: larger direction Hz) and vertically across it (positive: up, a smaller zenith angle).
COMPONENTS = ("range", "across", "vertical")
#: The terms of each harmonic, in that order.
TRIG = ("cos", "sin")
#: Prior RMS of the deviation over the viewing angles, per component, m: the centring
#: accuracy of 360-degree prisms (Leica: GRZ122 2 mm, GRZ4 5 mm; the deviations reach
#: several millimetres, Lackner and Lienhart 2016).
PRIOR_RMS_M = 2.0e-3
#: Prior standard deviation of each coefficient, m: the RMS shared by the harmonics' terms.
PRIOR_SIGMA_M = PRIOR_RMS_M / np.sqrt(len(TRIG) * len(ORDERS))
#: A harmonic of a prism is estimated where the prism's viewing azimuth sweeps at least this
#: many of its periods over the run (fewer: it is a constant and a slope there, the prism's
#: position and the clocks', and is held at 0).
MIN_PERIODS = 2.0
#: Prior standard deviation (m) holding a harmonic not estimated at 0.
HELD_SIGMA_M = 1e-7
#: A coefficient is determined by the data when its posterior sigma is at most this fraction
#: of its prior's (its information at least 3 times the prior's).
DETERMINED_RATIO = 0.5


def n_coefficients(orders: tuple[int, ...] = ORDERS) -> int:
    """Coefficients per prism: orders x terms x components, in the order
    ``(order, trig, component)`` (:data:`TRIG`, :data:`COMPONENTS`), the last fastest."""
    return len(orders) * len(TRIG) * len(COMPONENTS)


def viewing_azimuth_body(R_world_body: np.ndarray, t_world_body: np.ndarray,
                         p_body: np.ndarray, station_xyz: np.ndarray):
    """Azimuth (M,), rad, in the body frame of poses ``R_world_body`` (M, 3, 3),
    ``t_world_body`` (M, 3), of the direction from each prism at ``p_body`` (M, 3) (body
    frame) to its station at ``station_xyz`` (M, 3) (world), m, and its gradients:
    ``d alpha / d (rho, phi)`` (M, 6) of the pose's right perturbation ``T exp(xi^)`` (the
    joint engine's knots), ``d alpha / d station`` (M, 3) and ``d alpha / d p_body`` (M, 3)."""
    o = np.einsum("mji,mj->mi", R_world_body, station_xyz - t_world_body)  # station, body
    b = o - p_body  # prism to station, body frame
    rh2 = b[:, 0] ** 2 + b[:, 1] ** 2
    g = np.stack([-b[:, 1], b[:, 0], np.zeros_like(rh2)], axis=1) / rh2[:, None]  # d a / d b
    # b = R^T (s - t) - p: d b / d rho = -I, d b / d phi = o^ (R exp(phi^)), d b / d s = R^T
    d_phi = np.cross(g, o)  # g^T o^ = (g x o)^T
    d_xi = np.concatenate([-g, d_phi], axis=1)
    return np.arctan2(b[:, 1], b[:, 0]), d_xi, np.einsum("mij,mj->mi", R_world_body, g), -g


def deviation_jacobian(alpha: np.ndarray, v: np.ndarray, d: np.ndarray,
                       orders: tuple[int, ...] = ORDERS) -> tuple[np.ndarray, np.ndarray]:
    """``d (hz, v, d) / d coefficients`` (M, 3, C) of each measurement's prism's coefficients
    (:func:`n_coefficients`), at its viewing azimuth ``alpha`` (M,) rad, zenith ``v`` (M,)
    rad and distance ``d`` (M,) m: a deviation ``(r, a, u)`` m (:data:`COMPONENTS`) changes
    the distance by ``r``, the direction by ``a / (d sin v)`` and the zenith by ``-u / d``;
    and its derivative with respect to ``alpha`` (M, 3, C)."""
    k = np.asarray(orders, dtype=float)
    ka = alpha[:, None] * k[None, :]  # (M, O)
    c, s = np.cos(ka), np.sin(ka)
    trig = np.stack([c, s], axis=2)  # (M, O, 2)
    slope = np.stack([-k * s, k * c], axis=2)
    per = np.stack([1.0 / (d * np.sin(v)), -1.0 / d, np.ones_like(d)], axis=1)  # hz, v, d
    M = alpha.size
    out = []
    for f in (trig, slope):
        J = np.zeros((M, 3, len(orders), len(TRIG), len(COMPONENTS)))
        for row, comp in ((0, 1), (1, 2), (2, 0)):  # hz <- across, v <- vertical, d <- range
            J[:, row, :, :, comp] = f * per[:, row, None, None]
        out.append(J.reshape(M, 3, -1))
    return out[0], out[1]


def deviation_prior_sigma(alpha: np.ndarray, prism: np.ndarray, n_prisms: int,
                          orders: tuple[int, ...] = ORDERS) -> np.ndarray:
    """Prior sigma (P, C) m of each prism's coefficients from the viewing azimuths ``alpha``
    (M,) rad of its measurements (``prism`` (M,) indices, in time order):
    :data:`PRIOR_SIGMA_M` for a harmonic whose periods the azimuth sweeps at least
    :data:`MIN_PERIODS` times (its span unwrapped along the time), :data:`HELD_SIGMA_M`
    (held at 0) for the others."""
    span = np.zeros(n_prisms)
    for j in range(n_prisms):  # a handful of prisms
        a = np.unwrap(alpha[prism == j])
        span[j] = a.max() - a.min() if a.size else 0.0
    periods = span[:, None] * np.asarray(orders, dtype=float)[None, :] / (2.0 * np.pi)
    sigma = np.where(periods >= MIN_PERIODS, PRIOR_SIGMA_M, HELD_SIGMA_M)  # (P, O)
    return np.repeat(sigma, len(TRIG) * len(COMPONENTS), axis=1)


def deviation_chain(dev: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``L`` (M, 3, 3) such that ``L H`` is the Jacobian of ``h + dev`` where ``H`` is that of
    the prediction ``h = (hz, v, d)`` (zenith ``v`` (M,) rad, distance ``d`` (M,) m) and
    ``dev`` (M, 3) the deviation's change of it at fixed coefficients and azimuth
    (:func:`deviation_jacobian`): its direction's ``a / (d sin v)`` and zenith's ``-u / d``
    change with ``v`` and ``d``."""
    L = np.broadcast_to(np.eye(3), dev.shape[:1] + (3, 3)).copy()
    L[:, 0, 1] = -dev[:, 0] / np.tan(v)  # d (a / (d sin v)) / d v
    L[:, 0, 2] = -dev[:, 0] / d
    L[:, 1, 2] = -dev[:, 1] / d  # d (-u / d) / d d
    return L


@dataclass(frozen=True)
class DeviationFit:
    """The prisms' estimated deviation: ``names`` (P,) the prisms, ``orders`` the harmonics,
    ``coef`` (P, C) m (:func:`n_coefficients`' order), ``cov`` (P C, P C) m^2 their
    covariance, ``prior_sigma`` (P, C) m their prior's (:func:`deviation_prior_sigma`)."""

    names: tuple[str, ...]
    orders: tuple[int, ...]
    coef: np.ndarray
    cov: np.ndarray
    prior_sigma: np.ndarray

    @property
    def sigma(self) -> np.ndarray:
        """Sigmas (P, C) of the coefficients, m."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None)).reshape(self.coef.shape)

    @property
    def determined(self) -> np.ndarray:
        """Which coefficients (P, C) the data determine (:data:`DETERMINED_RATIO`)."""
        return self.sigma <= DETERMINED_RATIO * self.prior_sigma

    @property
    def held(self) -> np.ndarray:
        """Which coefficients (P, C) were held at 0 (:data:`MIN_PERIODS`)."""
        return self.prior_sigma <= HELD_SIGMA_M

    def amplitude(self) -> np.ndarray:
        """Amplitude (P, O, 3) m of each prism's harmonic per component,
        ``sqrt(cos^2 + sin^2)``."""
        c = self.coef.reshape(len(self.names), len(self.orders), len(TRIG), len(COMPONENTS))
        return np.hypot(c[:, :, 0], c[:, :, 1])


__all__ = ["COMPONENTS", "DETERMINED_RATIO", "DeviationFit", "HELD_SIGMA_M", "MIN_PERIODS",
           "ORDERS", "PRIOR_RMS_M", "PRIOR_SIGMA_M", "TRIG", "deviation_chain",
           "deviation_jacobian", "deviation_prior_sigma", "n_coefficients",
           "viewing_azimuth_body"]
