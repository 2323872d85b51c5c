"""The white measurement noise identified from the joint residuals: per station and channel
(Hz, V, d) a variance factor of the datasheet's variance and a range-dependent part, by
iterated variance components (REML) with redundancy numbers: docs/joint.md#noise-identification.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

#: Channels of a polar measurement, in the order of its rows.
CHANNELS = ("hz", "v", "d")
#: Range in which the angles' range part is stated (variance per this much range), m.
RANGE_UNIT_M = 100.0
#: Least redundancy share of a datasheet factor to be estimated; below it, it keeps its prior
#: and is flagged (as the ``Qc`` groups' ``MIN_REDUNDANCY``).
MIN_REDUNDANCY = 10.0
#: One-sided score-test threshold for a range part to enter (false alarm 1e-3 per component,
#: as the prisms' test).
SCORE_Z = float(norm.ppf(1.0 - 1e-3))
#: Smallest variance factor of the datasheet part (a positive definite covariance).
FACTOR_FLOOR = 1e-4
#: The prior: the datasheet's variance (factor 1), no range part.
PRIOR = np.array([1.0, 0.0])


@dataclass(frozen=True)
class NoiseFit:
    """Per station (S, in the problem's order) and channel (:data:`CHANNELS`) the components
    ``theta`` (S, 3, 2): ``[..., 0]`` the factor of the datasheet's white variance, ``[..., 1]``
    the range part (angles: rad^2 per :data:`RANGE_UNIT_M` of range, variance
    ``theta_1 d / 100 m``; distance: ppm^2, variance ``theta_1 (1e-6 d)^2``); ``sigma`` (S, 3,
    2) their standard deviations; ``determined`` (S, 3, 2) those estimated (else the prior,
    flagged); ``redundancy`` (S, 3, 2) each component's redundancy share; ``iterations``;
    ``stations`` (S,) their ids (where known); ``cov`` (S, 6, 6) the covariance of each
    station's six (channel-major: ``theta[s].ravel()``), zero where not determined;
    ``median_basis`` (S, 3, 2) :func:`noise_basis` at each station's median (the channel's
    variance there is ``theta @ median_basis``); ``pooled`` (S, 3) the factors that are one
    factor of their channel's pooled stations (docs/joint.md#pooled-factors; None: none)."""

    theta: np.ndarray
    sigma: np.ndarray
    determined: np.ndarray
    redundancy: np.ndarray
    iterations: int
    stations: tuple[str, ...] = ()
    cov: np.ndarray | None = None
    median_basis: np.ndarray | None = None
    pooled: np.ndarray | None = None

    @property
    def median_range_m(self) -> np.ndarray:
        """Each station's median range (S,), m: where :meth:`median_variance` holds."""
        return RANGE_UNIT_M * self.median_basis[:, 0, 1]

    def median_variance(self) -> tuple[np.ndarray, np.ndarray]:
        """Each channel's white variance (S, 3) at its station's median and its standard
        deviation (S, 3) (first order; zero where not determined)."""
        B = self.median_basis
        v = np.einsum("sck,sck->sc", self.theta, B)
        g = B * self.determined
        S = B.shape[0]
        cov = np.zeros((S, 6, 6)) if self.cov is None else self.cov
        sd = np.stack([np.sqrt(np.einsum("si,sij,sj->s", g[:, c], cov[:, 2 * c:2 * c + 2,
                                                                     2 * c:2 * c + 2], g[:, c]))
                       for c in range(3)], axis=1)
        return v, sd

    @property
    def range_sigma(self) -> np.ndarray:
        """The range parts as sigmas (S, 3): angles rad at 100 m, distance ppm."""
        return np.sqrt(np.clip(self.theta[..., 1], 0.0, None))


def noise_basis(var_white: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Variance per unit component (M, 3, 2) of each channel: the datasheet's ``var_white``
    (M, 3) and the range part, ``d / 100 m`` for the angles (turbulence: the variance of the
    angle of arrival grows with the path length), ``(1e-6 d)^2`` for the distance (a scale
    error), ``d`` (M,) m."""
    Q = np.empty(var_white.shape + (2,))
    Q[:, :, 0] = var_white
    Q[:, :2, 1] = (d / RANGE_UNIT_M)[:, None]
    Q[:, 2, 1] = (1e-6 * d) ** 2
    return Q


def measurement_cov(corr: np.ndarray, Q: np.ndarray, station: np.ndarray,
                    theta: np.ndarray) -> np.ndarray:
    """White covariance (M, 3, 3) of channel variances ``sum_k theta[station, c, k]
    Q[:, c, k]`` and the datasheet's correlation ``corr`` (M, 3, 3) between the channels."""
    sd = np.sqrt(np.einsum("mck,mck->mc", Q, theta[station]))
    return corr * sd[:, :, None] * sd[:, None, :]


def component_sums(e: np.ndarray, W: np.ndarray, HSH: np.ndarray, Q: np.ndarray,
                   cov_rest: np.ndarray, station: np.ndarray, n_stations: int):
    """Per station the quadratic forms ``q`` (S, 6) ``e^T W Q_i W e`` less the channels'
    correlations' share ``tr(W_P Q_i W cov_rest)``, unit redundancies
    ``r`` (S, 6) ``tr(W_P Q_i)`` and the metric ``F`` (S, 6, 6) ``tr(W_P Q_i W Q_j)`` of its
    six components (channel-major), summed over its measurements.

    ``e`` (M, 3) residuals, ``W`` (M, 3, 3) their weights, ``HSH`` (M, 3, 3) the covariance
    of their fitted values (``H Sigma H^T``), ``W_P = W - W HSH W`` (the diagonal blocks of the
    residuals' weight); ``Q`` (M, 3, 2) :func:`noise_basis`, ``cov_rest`` (M, 3, 3) the
    covariance's off-diagonal part (held while the channels' variances are updated).
    """
    We = np.einsum("mij,mj->mi", W, e)
    WP = W - W @ HSH @ W
    Qf = Q.reshape(-1, 6)  # component i = 2 c + k on channel c = i // 2
    ch = np.arange(6) // 2
    q_m = (We[:, ch] ** 2 - np.einsum("mcc->mc", W @ cov_rest @ WP)[:, ch]) * Qf
    r_m = np.einsum("mcc->mc", WP)[:, ch] * Qf
    F_m = WP[:, ch][:, :, ch] * np.swapaxes(W[:, ch][:, :, ch], 1, 2) * Qf[:, :, None] \
        * Qf[:, None, :]
    q = np.zeros((n_stations, 6))
    r = np.zeros((n_stations, 6))
    F = np.zeros((n_stations, 6, 6))
    np.add.at(q, station, q_m)
    np.add.at(r, station, r_m)
    np.add.at(F, station, F_m)
    return q, r, 0.5 * (F + np.swapaxes(F, 1, 2))


def range_scores(q: np.ndarray, r: np.ndarray, F: np.ndarray, th: np.ndarray,
                 determined: np.ndarray) -> np.ndarray:
    """Score test (Rao) of each range part at its prior 0 (S, 3, 2; 0 for the factors and the
    range parts already in): ``(g_1 - F_10 / F_00 g_0) / sqrt(2 (F_11 - F_10^2 / F_00))``,
    ``g = q - F theta`` (the REML score, :func:`component_sums`), the channel's factor the
    nuisance where it is estimated."""
    S = th.shape[0]
    g = q - np.einsum("sij,sj->si", F, th)
    z = np.zeros((S, 3, 2))
    for c in range(3):
        i0, i1 = 2 * c, 2 * c + 1
        nuis = determined[:, c, 0]
        f00 = np.where(nuis, F[:, i0, i0], 1.0)
        f10 = np.where(nuis, F[:, i1, i0], 0.0)
        var = 2.0 * (F[:, i1, i1] - f10**2 / f00)
        score = g[:, i1] - f10 / f00 * g[:, i0]
        ok = (var > 0) & ~determined[:, c, 1]
        z[:, c, 1] = np.where(ok, score / np.sqrt(np.where(ok, var, 1.0)), 0.0)
    return z


def update_components(theta: np.ndarray, q: np.ndarray, r: np.ndarray, F: np.ndarray,
                      determined: np.ndarray | None = None,
                      pooled: np.ndarray | None = None):
    """One REML step from ``theta`` (S, 3, 2) and the sums of :func:`component_sums`:
    ``F_dd theta_d = q_d - F_du theta_u`` over each station's determined components ``d``
    (the others ``u`` at their prior or at the channel's pooled factor), floored. Its fixed
    point is the REML equations ``e^T W Q_i W e = tr(W_P Q_i)``; for a single component it
    is Förstner's ``theta q / r``. A station's factor is determined once its redundancy share
    ``theta_i r_i`` reaches :data:`MIN_REDUNDANCY` (at any update; it stays determined); the
    factors of a channel that the stations do not determine alone are one factor of those
    stations, ``pooled`` (S, 3), once their shares together reach it (the datasheet is
    common: docs/joint.md#pooled-factors; a pooled station leaves once its share alone
    reaches it, the others stay pooled), solved after the stations' own components with theirs
    held (block Gauss-Seidel: the loop's next update corrects). A range part is determined
    once its score test at 0 (:func:`range_scores`) passes :data:`SCORE_Z`, from the second
    update on (at the prior's weights the statistic's spread follows the factors' error,
    docs/joint.md#noise-identification). ``determined``, ``pooled``: the last update's
    (None: the first). Returns ``theta``, their sigmas (S, 3, 2) from ``2 F_dd^-1``, the
    determined components (a pooled factor among them), the redundancy shares (S, 3, 2), the
    covariance (S, 6, 6) and the pooled factors (S, 3)."""
    S = theta.shape[0]
    th = theta.reshape(S, 6)
    share = th * r
    share3 = share.reshape(S, 3, 2)
    if determined is None:  # the weights are the prior's: no range part is tested yet
        determined = np.zeros((S, 3, 2), bool)
    else:
        determined = determined | (range_scores(q, r, F, th, determined) >= SCORE_Z)
    was = np.zeros((S, 3), bool) if pooled is None else pooled
    alone = share3[:, :, 0] >= MIN_REDUNDANCY
    determined[:, :, 0] |= alone  # (a pooled station whose share now suffices leaves)
    rest = ~determined[:, :, 0] | (was & ~alone)  # the stations a pooled factor is of
    together = np.where(rest, share3[:, :, 0], 0.0).sum(axis=0) >= MIN_REDUNDANCY
    pooled = rest & (together | was.any(axis=0))[None, :]
    determined[:, :, 0] |= pooled
    det = determined.reshape(S, 6)
    own = det & ~(np.repeat(pooled, 2, axis=1) & np.tile([True, False], 3))
    prior = np.tile(PRIOR, 3)
    new = np.where(det, th, prior[None, :])
    cov = np.zeros((S, 6, 6))
    floor = np.tile([FACTOR_FLOOR, 0.0], 3)
    for s in range(S):
        d, u = own[s], ~own[s]
        if not d.any():
            continue
        Fdd = F[s][np.ix_(d, d)]
        new[s, d] = np.maximum(np.linalg.solve(Fdd, q[s, d] - F[s][np.ix_(d, u)] @ new[s, u]),
                               floor[d])
        cov[s][np.ix_(d, d)] = 2.0 * np.linalg.inv(Fdd)
    for c in np.flatnonzero(pooled.any(axis=0)):  # a channel's pooled factor, the rest held
        i, of = 2 * c, pooled[:, c]
        others = np.arange(6) != i
        f = F[of, i, i].sum()
        g = (q[of, i] - np.einsum("sj,sj->s", F[of, i][:, others], new[of][:, others])).sum()
        new[of, i] = max(g / f, FACTOR_FLOOR)
        cov[of, i, i] = 2.0 / f
    sigma = np.sqrt(np.clip(np.einsum("sii->si", cov), 0.0, None))
    return (new.reshape(S, 3, 2), sigma.reshape(S, 3, 2), determined, share3, cov, pooled)


__all__ = ["CHANNELS", "FACTOR_FLOOR", "MIN_REDUNDANCY", "NoiseFit", "PRIOR", "RANGE_UNIT_M",
           "SCORE_Z", "component_sums", "measurement_cov", "noise_basis", "range_scores",
           "update_components"]
