"""The stations' clock offsets estimated from the rigid body: each station's clock against the
reference station's, as a function of time, from the inter-prism distances of a moving robot.

A station whose clock runs ``e`` seconds ahead records its prism where it was ``e`` earlier, so
the distance between two prisms tracked by different stations is off by the relative motion
times the offsets. Owns :func:`estimate_clock_offsets` (weighted least squares of the distance
residuals on a piecewise-linear offset per station with a random-walk prior, a constant
distance bias per pair, the sigma scaled by the residuals and their correlation in time) and
:class:`ClockEstimate`. Model, assumptions and measurements: docs/clocks.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.checks.distances import effective_sample_size
from rtsgt.errors import InputError

__all__ = ["KNOT_SPACING_S", "LEVEL_SIGMA_S", "RATE_SIGMA", "RATE_WALK_S2_PER_S3", "WALK_S2_PER_S",
           "ClockEstimate", "estimate_clock_offsets", "level_rate_noise",
           "walk_prior_info"]

#: Spacing of the knots of each station's piecewise-linear clock offset, s: a clock that
#: drifts is linear between them, and its random walk moves it by about
#: ``sqrt(WALK_S2_PER_S * KNOT_SPACING_S)`` from one to the next.
KNOT_SPACING_S = 60.0
#: Intensity of the prior random walk of a clock offset, s^2/s (white frequency noise): about
#: 2 ms an hour, above the walk of the quartz clocks of the stations' controllers and loggers.
WALK_S2_PER_S = 1.0e-9
#: Intensity of the prior random walk of a clock's rate, s^2/s^3 (random-walk frequency
#: noise): the rate may change by about 10 ppm an hour.
RATE_WALK_S2_PER_S3 = 2.8e-14
#: Prior sigma of the level of each clock offset, s (a bound, not information).
LEVEL_SIGMA_S = 1.0
#: Prior sigma of each clock's rate at its first knot, s/s (a bound, not information: a
#: quartz oscillator's tolerance is tens of ppm): a constant drift costs next to nothing.
RATE_SIGMA = 1.0e-4


@dataclass(frozen=True)
class ClockEstimate:
    """Each station's clock offset against the reference station, piecewise linear in time.

    ``stations`` the stations estimated (the others than ``reference``); ``knots_s`` (K,)
    the knot times, s; ``offset_s`` (S, K) the offset of each station at each knot, s (its
    clock minus the reference's: it time-stamps an event that late); ``cov`` (S K, S K) their
    covariance, s^2, in the order of ``offset_s.ravel()``; ``pair_bias_m`` the constant
    distance bias of each pair of prisms with its sigma, m; ``variance_factor`` the residuals'
    chi^2 per degree of freedom; ``correlation_factor`` the poses per effective sample of the
    whitened residuals (both scale ``cov``); ``poses`` the poses used.
    """

    reference: str
    stations: tuple[str, ...]
    knots_s: np.ndarray
    offset_s: np.ndarray
    cov: np.ndarray
    pair_bias_m: dict[str, tuple[float, float]]
    variance_factor: float
    correlation_factor: float
    poses: int

    def at(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Offset (S, N) and its sigma (S, N), s, of every estimated station at the times
        ``t`` (N,), s (held constant before the first knot and after the last)."""
        B = _hat_basis(np.asarray(t, dtype=float), self.knots_s)  # (N, K)
        S, K = self.offset_s.shape
        mean = self.offset_s @ B.T
        cov = self.cov.reshape(S, K, S, K)
        var = np.einsum("nk,sksl,nl->sn", B, cov, B)
        return mean, np.sqrt(np.maximum(var, 0.0))

    def as_dict(self) -> dict:
        """JSON-ready: per station the knots' offsets and sigmas (ms), the pair biases (mm)
        and the scale factors."""
        sigma = np.sqrt(np.diag(self.cov)).reshape(self.offset_s.shape)
        return {
            "reference": self.reference,
            "knot_spacing_s": float(np.median(np.diff(self.knots_s))) if self.knots_s.size > 1
            else None,
            "knots_s": self.knots_s.tolist(),
            "stations": {s: {"offset_ms": (1e3 * self.offset_s[k]).tolist(),
                             "sigma_ms": (1e3 * sigma[k]).tolist()}
                         for k, s in enumerate(self.stations)},
            "pair_bias_mm": {p: [1e3 * b, 1e3 * s] for p, (b, s) in self.pair_bias_m.items()},
            "variance_factor": self.variance_factor,
            "correlation_factor": self.correlation_factor,
            "poses": self.poses,
        }


def _hat_basis(t: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Linear interpolation weights (N, K) of the times ``t`` on the ``knots`` (each row sums
    to 1; constant outside)."""
    K = knots.size
    B = np.zeros((t.size, K))
    if K == 1:
        B[:, 0] = 1.0
        return B
    tc = np.clip(t, knots[0], knots[-1])
    k = np.clip(np.searchsorted(knots, tc, side="right") - 1, 0, K - 2)
    w = (tc - knots[k]) / (knots[k + 1] - knots[k])
    rows = np.arange(t.size)
    B[rows, k] = 1.0 - w
    B[rows, k + 1] = w
    return B


def _knots(t: np.ndarray, spacing: float) -> np.ndarray:
    """Knots from the first to the last time, about ``spacing`` apart (at least two)."""
    span = float(t[-1] - t[0])
    n = max(2, int(np.ceil(span / spacing)) + 1)
    return np.linspace(t[0], t[-1], n)


def _residuals(xyz, vel, cov, body, pairs):
    """Per pose and pair: the distance residual ``|q_i - q_j| - |b_i - b_j|`` (T, P), m, its
    variance from the prisms' covariances (T, P), m^2, and the sensitivities to prism i's and
    prism j's clock offsets, ``-u . v_i`` and ``u . v_j`` (T, P) each, m/s."""
    i, j = np.array(pairs).T
    d = xyz[:, i] - xyz[:, j]  # (T, P, 3)
    length = np.linalg.norm(d, axis=-1)
    u = d / length[..., None]
    r = length - np.linalg.norm(body[i] - body[j], axis=-1)
    var = np.einsum("tpa,tpab,tpb->tp", u, cov[:, i] + cov[:, j], u)
    return r, var, -np.einsum("tpa,tpa->tp", u, vel[:, i]), np.einsum("tpa,tpa->tp", u, vel[:, j])


def estimate_clock_offsets(
    t: ArrayLike, xyz: ArrayLike, vel: ArrayLike, cov: ArrayLike, body: ArrayLike,
    station_of: list[str], reference: str, *, knot_spacing_s: float = KNOT_SPACING_S,
    walk_s2_per_s: float = WALK_S2_PER_S, rate_walk_s2_per_s3: float = RATE_WALK_S2_PER_S3,
) -> ClockEstimate:
    """The clock offset of each station against ``reference`` (module docstring).

    Parameters
    ----------
    t : (T,) pose times, s, increasing
    xyz, vel : (T, n, 3) each prism's interpolated position, m, and velocity, m/s
    cov : (T, n, 3, 3) each prism's position covariance, m^2 (the weights)
    body : (n, 3) the prisms' surveyed positions on the robot, m
    station_of : the station tracking each prism (n entries)
    reference : the station whose clock the others are measured against

    Returns
    -------
    ClockEstimate

    Raises
    ------
    InputError
        Fewer than two prisms, a station of no prism as reference, or too few poses.
    """
    t = np.asarray(t, dtype=float)
    xyz, vel, cov = (np.asarray(a, dtype=float) for a in (xyz, vel, cov))
    body = np.asarray(body, dtype=float)
    n = xyz.shape[1]
    if n < 2 or reference not in station_of or t.size < 10:
        raise InputError(f"Expected at least two prisms, the reference station {reference!r} "
                         f"among their stations and 10 poses, got {n} prisms of "
                         f"{sorted(set(station_of))} and {t.size} poses")
    stations = tuple(s for s in dict.fromkeys(station_of) if s != reference)
    pairs = list(combinations(range(n), 2))
    r, var, a_i, a_j = _residuals(xyz, vel, cov, body, pairs)
    knots = _knots(t, knot_spacing_s)
    K, S, P = knots.size, len(stations), len(pairs)
    B = _hat_basis(t, knots)
    # columns: the offsets of each station at each knot, then one distance bias per pair
    A = np.zeros((t.size, P, S * K + P))
    for p, (i, j) in enumerate(pairs):
        for prism, sens in ((i, a_i[:, p]), (j, a_j[:, p])):
            if station_of[prism] != reference:
                s = stations.index(station_of[prism])
                A[:, p, s * K:(s + 1) * K] += sens[:, None] * B
        A[:, p, S * K + p] = 1.0
    w = 1.0 / var
    A2 = A.reshape(-1, S * K + P)
    N = A2.T @ (A2 * w.reshape(-1, 1))
    g = A2.T @ (w * r).ravel()
    N[:S * K, :S * K] += _walk_prior(knots, S, walk_s2_per_s, rate_walk_s2_per_s3)
    x = np.linalg.solve(N, g)
    z = (r - A @ x) / np.sqrt(var)  # (T, P) whitened residuals, in time order
    dof = max(z.size - (S * K + P), 1)
    variance_factor = float(np.sum(z * z) / dof)
    # the estimate is a weighted sum of the residuals times their sensitivities: the
    # correlation in time that matters is that of these products (the score contributions)
    score = np.einsum("tpc,tp->tc", A[:, :, :S * K], z / np.sqrt(var))
    per_station = score.reshape(t.size, S, K).sum(axis=2)
    correlation_factor = float(max(t.size / effective_sample_size(per_station[:, [k]])
                                   for k in range(S)))
    cov_x = np.linalg.inv(N) * max(variance_factor, 1.0) * max(correlation_factor, 1.0)
    sig = np.sqrt(np.diag(cov_x))
    names = [f"{pi}-{pj}" for pi, pj in pairs]
    return ClockEstimate(
        reference=reference, stations=stations, knots_s=knots,
        offset_s=x[:S * K].reshape(S, K), cov=cov_x[:S * K, :S * K],
        pair_bias_m={names[p]: (float(x[S * K + p]), float(sig[S * K + p])) for p in range(P)},
        variance_factor=variance_factor, correlation_factor=correlation_factor, poses=t.size)


def _walk_prior(knots: np.ndarray, S: int, q: float, q_rate: float) -> np.ndarray:
    """Information (S K, S K) of the prior of each of ``S`` stations' knots
    (:func:`walk_prior_info`)."""
    return np.kron(np.eye(S), walk_prior_info(knots, q, q_rate))


def level_rate_noise(dt: np.ndarray, q: float, q_rate: float) -> np.ndarray:
    """Covariance (N, 2, 2) of ``(level, rate)`` gathered over intervals ``dt`` (N,) s by a
    random walk of the level of intensity ``q`` (unit^2/s) plus the integral of a random walk
    of the rate of intensity ``q_rate`` (unit^2/s^3): ``[[q dt + q_rate dt^3/3,
    q_rate dt^2/2], [q_rate dt^2/2, q_rate dt]]`` (the transition is ``[[1, dt], [0, 1]]``)."""
    dt = np.asarray(dt, dtype=float)
    Q = np.empty(dt.shape + (2, 2))
    Q[..., 0, 0] = q * dt + q_rate * dt**3 / 3.0
    Q[..., 0, 1] = Q[..., 1, 0] = q_rate * dt**2 / 2.0
    Q[..., 1, 1] = q_rate * dt
    return Q


def walk_prior_info(knots: np.ndarray, q: float = WALK_S2_PER_S,
                    q_rate: float = RATE_WALK_S2_PER_S3, level_sigma: float = LEVEL_SIGMA_S,
                    rate_sigma: float = RATE_SIGMA) -> np.ndarray:
    """Information (J, J) of one clock's offsets at ``knots`` (J,) s, increasing: the offset
    is a level (sigma ``level_sigma`` s) plus a drift (its rate at the first knot of sigma
    ``rate_sigma`` s/s) plus a random walk of intensity ``q`` (s^2/s) plus the integral of a
    random walk of the rate of intensity ``q_rate`` (s^2/s^3, > 0): the sum of the processes,
    not the product of their priors (a constant drift costs next to nothing). The offset and
    rate at the knots are Markov (transition ``[[1, dt], [0, 1]]``, noise covariance
    ``[[q dt + q_rate dt^3/3, q_rate dt^2/2], [q_rate dt^2/2, q_rate dt]]``); the rates are
    marginalised (Schur complement). docs/clocks.md#the-prior."""
    knots = np.asarray(knots, dtype=float)
    J = knots.size
    A = np.zeros((2 * J, 2 * J))  # (offsets, rates)
    A[0, 0] += 1.0 / level_sigma**2
    A[J, J] += 1.0 / rate_sigma**2
    if J > 1:
        dt = np.diff(knots)
        Q = level_rate_noise(dt, q, q_rate)
        M = np.zeros((J - 1, 2, 4))  # x_k+1 - F x_k over (e_k, r_k, e_k+1, r_k+1)
        M[:, 0, 0] = M[:, 1, 1] = -1.0
        M[:, 0, 1] = -dt
        M[:, 0, 2] = M[:, 1, 3] = 1.0
        blocks = np.swapaxes(M, 1, 2) @ np.linalg.solve(Q, M)
        k = np.arange(J - 1)
        idx = np.stack([k, J + k, k + 1, J + k + 1], axis=1)
        np.add.at(A, (idx[:, :, None], idx[:, None, :]), blocks)
    info = A[:J, :J] - A[:J, J:] @ np.linalg.solve(A[J:, J:], A[J:, :J])
    return 0.5 * (info + info.T)
