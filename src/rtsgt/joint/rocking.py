"""The vehicle's rocking: a first-order Gauss-Markov process per axis of the knots' pose,
added to the pose every measurement sees, carried as states of the knots.

A vehicle rocks on its suspension faster than one prism at a time can follow; with the
rocking taken for the stations' white noise, the model's cost prefers a wrong body frame
(docs/joint.md#the-vehicles-rocking). Axes as the pose's right perturbation (shifts along
x, y, z, then rotations about them: rtsgt.joint.se3's order), each its own chain with the
:mod:`rtsgt.joint.gm` process, its sigma and correlation time estimated as the noise
chains' are (:func:`rtsgt.joint.gm.update`: the model's rows are the shifts and the
rotations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.interpolation.motion import STANDING_SPEED_M_S
from rtsgt.joint import gm as gmn
from rtsgt.joint.se3 import exp_se3
from rtsgt.joint.sparse import ArrowSolution, chunks

#: The rocking's chains per knot: shifts along x, y, z (m), rotations about them (rad).
ROCKING_DIM = 6
#: Starting sigma of the shifts' chains, m, and of the rotations', rad: a rocking vehicle's
#: size (docs/simulation.md#the-vehicles-rocking); the data decide from there.
START_SIGMA_M = 1e-3
START_SIGMA_RAD = 1e-3
#: Starting correlation time, s: a suspension's period, 0.3-2 s.
START_TAU_S = 0.3
#: Bounds of the rocking's speed-law exponent (:class:`SpeedLaw`): 0 a rocking whose size
#: does not change with the speed, 1 one proportional to it
#: (docs/joint.md#the-rockings-speed-law).
EXPONENT_RANGE = (0.0, 2.0)
#: Largest change of the exponent in one step.
MAX_EXPONENT_STEP = 0.5
#: Step of the exponent's numerical derivatives.
_H = 1e-3


@dataclass(frozen=True)
class SpeedLaw:
    """The rocking's size along the run: at a knot whose fastest prism moves at ``v`` m/s,
    ``scale = (max(v, floor) / reference_speed_m_s) ** exponent`` times the chains' (their
    sigma is the rocking's at the reference speed, the median of the moving knots'; the
    floor :data:`rtsgt.interpolation.motion.STANDING_SPEED_M_S`, a standing vehicle's);
    ``exponent_sd`` its standard deviation (0 where not estimated)."""

    exponent: float
    reference_speed_m_s: float
    exponent_sd: float = 0.0

    def scale(self, speed: np.ndarray) -> np.ndarray:
        """The law's scale (K,) at speeds ``speed`` (K,) m/s."""
        v = np.maximum(np.asarray(speed, dtype=float), STANDING_SPEED_M_S)
        return (v / self.reference_speed_m_s) ** self.exponent


def reference_speed(speed: np.ndarray) -> float:
    """The median speed (m/s) of the knots faster than a standing vehicle (``speed`` (K,));
    1 m/s where none moves."""
    moving = speed[speed >= STANDING_SPEED_M_S]
    return float(np.median(moving)) if moving.size else 1.0


def _loglik(beta, v_ref, speed, model: gmn.GaussMarkov, rock, var, cross, dt) -> np.ndarray:
    """The expected complete-data log-likelihood (R,) of the rocking under the law of
    exponent ``beta``: its chains ``z = r / scale`` under ``model`` plus the change of
    variables' ``-sum_k log scale_k`` per axis; ``rock`` (K, 6 R) R sets of means (draws),
    ``var``, ``cross`` their posterior moments (zero for draws)."""
    a = SpeedLaw(beta, v_ref).scale(speed)
    z = scaled_moments(rock, var, cross, a)
    reps = rock.shape[1] // 6
    x = np.tile(np.stack([2.0 * np.log(model.sigma.ravel()), np.log(model.tau_s.ravel())], 1),
                (reps, 1))
    q = gmn.expected_loglik(x[:, 0], x[:, 1], *z, dt).reshape(reps, 6)
    return q.sum(axis=1) - 6.0 * np.sum(np.log(a))


def speed_law_step(law: SpeedLaw, model: gmn.GaussMarkov, rock: np.ndarray, var: np.ndarray,
                   cross: np.ndarray, dt: np.ndarray, speed: np.ndarray,
                   rng: np.random.Generator | None = None,
                   n_draws: int = gmn.N_DRAWS) -> SpeedLaw:
    """One Newton step of the law's exponent on the marginal likelihood of the data, from
    the rocking's posterior at every knot under ``law`` and ``model`` (means ``rock`` (K, 6),
    variances ``var`` (K, 6), consecutive covariances ``cross`` (K-1, 6), intervals ``dt``
    (K-1,) s; the knots' speeds ``speed`` (K,) m/s, whose moving median becomes the
    reference): the exact score (Fisher's identity: the derivative of the expected
    complete-data log-likelihood at the current exponent) over Louis' observed information
    (the complete data's less the posterior variance of its score over ``rng``'s ``n_draws``
    draws, :func:`rtsgt.joint.gm.posterior_draws`). Not EM's maximisation: where the data
    hardly see the rocking (its posterior is mostly its prior) that would keep any exponent
    it starts from. A step is at most :data:`MAX_EXPONENT_STEP`, within
    :data:`EXPONENT_RANGE`; without ``rng``, where the information is not positive or where
    no knot moves (every scale the floor's: the exponent and the chains' sigma are one), the
    law stays (with its last ``exponent_sd``)."""
    if not np.any(speed >= STANDING_SPEED_M_S):  # no knot moves: the law is not seen
        return SpeedLaw(law.exponent, reference_speed(speed), law.exponent_sd)
    v_ref = reference_speed(speed)
    beta = law.exponent
    f = [_loglik(beta + i * _H, v_ref, speed, model, rock, var, cross, dt)[0]
         for i in (-1, 0, 1)]
    score = (f[2] - f[0]) / (2.0 * _H)
    complete = -(f[2] - 2.0 * f[1] + f[0]) / _H**2
    if rng is None:
        return SpeedLaw(beta, v_ref, law.exponent_sd)
    draws = gmn.posterior_draws(rock, var, cross, rng, n_draws)  # (K, 6, R)
    flat = np.swapaxes(draws, 1, 2).reshape(rock.shape[0], -1)  # (K, R 6): draw-major
    zero_v, zero_c = np.zeros_like(flat), np.zeros((cross.shape[0], flat.shape[1]))
    up = _loglik(beta + _H, v_ref, speed, model, flat, zero_v, zero_c, dt)
    down = _loglik(beta - _H, v_ref, speed, model, flat, zero_v, zero_c, dt)
    info = complete - np.var((up - down) / (2.0 * _H), ddof=1)
    if not info > 0:
        return SpeedLaw(beta, v_ref, law.exponent_sd)
    step = float(np.clip(score / info, -MAX_EXPONENT_STEP, MAX_EXPONENT_STEP))
    return SpeedLaw(float(np.clip(beta + step, *EXPONENT_RANGE)), v_ref,
                    float(1.0 / np.sqrt(info)))


def scaled_moments(rock: np.ndarray, var: np.ndarray, cross: np.ndarray, scale: np.ndarray):
    """The moments of ``z = r / scale`` (``scale`` (K,)) from those of ``r``: means (K, n),
    variances (K, n), consecutive covariances (K-1, n)."""
    s = scale[:, None]
    return rock / s, var / s**2, cross / (s[:-1] * s[1:])


def start_rocking() -> gmn.GaussMarkov:
    """The rocking's starting chains (:class:`rtsgt.joint.gm.GaussMarkov`, rows the shifts
    and the rotations, columns x, y, z), none determined."""
    sigma = np.array([[START_SIGMA_M] * 3, [START_SIGMA_RAD] * 3])
    return gmn.GaussMarkov(sigma, np.full((2, 3), START_TAU_S), sigma.copy(),
                           np.zeros((2, 3), bool))


def rocking_moments(rock: np.ndarray, cov: np.ndarray, cross: np.ndarray,
                    dt: np.ndarray) -> list:
    """The chains' posterior moments for :func:`rtsgt.joint.gm.update`, one per row of the
    model (shifts, rotations): from the chains' means ``rock`` (K, 6), marginal variances
    ``cov`` (K, 6) and consecutive covariances ``cross`` (K-1, 6) at every knot, intervals
    ``dt`` (K-1,) s (every knot holds a measurement: the complete data)."""
    return [(rock[:, 3 * i:3 * i + 3], cov[:, 3 * i:3 * i + 3], cross[:, 3 * i:3 * i + 3], dt)
            for i in range(2)]


def rocked_knots(R: np.ndarray, t: np.ndarray, rocking: np.ndarray, sol: ArrowSolution,
                 col: int) -> tuple[np.ndarray, np.ndarray, ArrowSolution]:
    """The knots' poses with their rocking, ``T_k exp(r_k^)`` (``R`` (K, 3, 3), ``t`` (K, 3),
    ``rocking`` (K, 6)), and ``sol`` with each knot's pose perturbation (its first 6 states)
    as the rocked pose's, ``xi_k + r_k`` (first order: ``r`` is millimetres and
    milliradians; the rocking's states at columns ``col:col+6``): ``M . M^T`` of the knots'
    covariances, ``M`` of the shared factor, all turned in place, a few thousand knots at a
    time (as :func:`rtsgt.joint.axes.body_solution`'s factor: the solution is not read
    unrocked after this, and the hour's arrays are not copied)."""
    dR, dp = exp_se3(rocking)
    j = slice(col, col + ROCKING_DIM)
    for a in (sol.cov, sol.cov_next, sol.cov_var, sol.cov_var_next):  # M a M^T
        for sl in chunks(a.shape[0]):
            a[sl, :6] += a[sl, j]
            a[sl, :, :6] += a[sl, :, j]
    for sl in chunks(sol.factor.shape[0]):  # M L
        sol.factor[sl, :6] += sol.factor[sl, j]
    return R @ dR, t + np.einsum("kij,kj->ki", R, dp), sol


def bridge_variance(t_query: np.ndarray, t_knot: np.ndarray, model: gmn.GaussMarkov,
                    scale: np.ndarray | None = None) -> np.ndarray:
    """The rocking's variance (Q, 6) at ``t_query`` (Q,) s given its values at the two knots
    of the interval (``t_knot`` (K,) s) about each: per axis ``sigma^2 (1 - phi_a^2)
    (1 - phi_b^2) / (1 - phi_a^2 phi_b^2)``, ``phi = exp(-h / tau)`` over the times ``h`` to
    the interval's knots (the process is Markov: the knots beyond add nothing); zero at a
    knot; times the speed law's ``scale`` (K,) at the knots squared, linear between them
    (None: 1). What the knots' poses with their rocking do not carry between them."""
    tq = np.asarray(t_query, dtype=float)
    k = np.clip(np.searchsorted(t_knot, tq, side="right") - 1, 0, t_knot.size - 2)
    sigma, tau = model.sigma.ravel(), model.tau_s.ravel()
    pa = np.exp(-2.0 * np.clip(tq - t_knot[k], 0.0, None)[:, None] / tau)
    pb = np.exp(-2.0 * np.clip(t_knot[k + 1] - tq, 0.0, None)[:, None] / tau)
    var = sigma**2 * (1.0 - pa) * (1.0 - pb) / np.maximum(1.0 - pa * pb, 1e-300)
    if scale is None:
        return var
    return var * np.interp(tq, t_knot, scale)[:, None] ** 2


__all__ = ["EXPONENT_RANGE", "MAX_EXPONENT_STEP", "ROCKING_DIM", "START_SIGMA_M",
           "START_SIGMA_RAD", "START_TAU_S", "SpeedLaw", "bridge_variance", "reference_speed",
           "rocked_knots", "rocking_moments", "scaled_moments", "speed_law_step",
           "start_rocking"]
