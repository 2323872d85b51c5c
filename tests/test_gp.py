"""Exact GP interpolation of prism tracks (WNOA prior): rtsgt.interpolation.gp.

References used here, all independent of the code under test:

- a dense batch GP built directly from the covariance kernel of the WNOA process
  (integrated Wiener process, ``Cov(p(s), p(t)) = (u^2 v / 2 - u^3 / 6) Qc`` ...), with the same
  prior on the first state (a proper Gaussian, or diffuse: universal kriging with a flat prior
  on the initial state), solved in extended precision (``np.longdouble``), good to better
  than 1e-10 on RTS-like tracks (the kernel form loses the digits of max prior variance / min
  posterior variance), and in exact rational arithmetic (``fractions.Fraction``, no rounding
  at all) on small, badly conditioned tracks;
- a sequential Kalman filter (exact diffuse start from the first two measurements) for the
  prediction-error decomposition of the marginal likelihood;
- simulation from the prior itself for coverage and for the estimation of Qc.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats

from _paths import EXAMPLE_TOML as EXAMPLE
from rtsgt.errors import ExtrapolationError, InputError
from rtsgt.interpolation import (
    GPTrack,
    as_qc,
    fit_qc,
    fit_track,
    log_marginal_likelihood,
    wnoa_phi,
    wnoa_q,
    wnoa_q_inv,
)
from rtsgt.types import PrismTrack

LD = np.longdouble
#: The reference is computed in extended precision where the platform has it (x86: 64-bit
#: mantissa); where ``longdouble`` is plain double the reference is only good to ~1e-9 itself.
EXTENDED = np.finfo(LD).eps < 1e-18
TOL = 1e-9 if EXTENDED else 1e-7
CHI2_95_3 = stats.chi2.ppf(0.95, 3)
CHI2_95_6 = stats.chi2.ppf(0.95, 6)


# --------------------------------------------------------------------------------------------
# Dense reference: extended precision, or exact rational arithmetic
# --------------------------------------------------------------------------------------------


def _num(a, exact):
    """Array of ``np.longdouble``, or of exact ``Fraction`` objects (``exact``)."""
    a = np.asarray(a, dtype=float)
    if not exact:
        return a.astype(LD)
    return np.array([Fraction(x) for x in a.reshape(-1).tolist()], dtype=object).reshape(a.shape)


def _log(x):
    if isinstance(x, Fraction):
        return math.log(x.numerator) - math.log(x.denominator)
    return np.log(x)


def _solve_spd(G, B):
    """``G^-1 B`` and ``log|G|`` by Gaussian elimination without pivoting (G is SPD)."""
    A, X = G.copy(), B.copy()
    n = A.shape[0]
    logdet = 0.0
    for j in range(n):
        logdet += _log(A[j, j])
        f = A[j + 1:, j] / A[j, j]
        A[j + 1:, j:] -= f[:, None] * A[j, j:][None, :]
        X[j + 1:] -= f[:, None] * X[j][None, :]
    for i in range(n - 1, -1, -1):
        X[i] = (X[i] - A[i, i + 1:] @ X[i + 1:]) / A[i, i]
    return X, logdet


def _iwp_coef(u, v):
    """2x2 ``c`` with ``Cov(x(u), x(v)) = kron(c, Qc)`` for the integrated Wiener process
    started at 0 with zero state (``x = [p; v]``, ``u, v >= 0``), elementwise."""
    u, v = np.broadcast_arrays(u, v)
    le = u <= v
    lo, hi = np.where(le, u, v), np.where(le, v, u)
    c = np.empty(u.shape + (2, 2), u.dtype)
    c[..., 0, 0] = lo * lo * hi / 2 - lo * lo * lo / 6  # int_0^lo (u - r)(v - r) dr
    c[..., 0, 1] = np.where(le, u * u / 2, u * v - v * v / 2)  # Cov(p(u), v(v))
    c[..., 1, 0] = np.where(le, u * v - u * u / 2, v * v / 2)  # Cov(v(u), p(v))
    c[..., 1, 1] = lo
    return c


def _kron(c, m):
    out = c[..., :, None, :, None] * m[..., None, :, None, :]
    return out.reshape(out.shape[:-4] + (6, 6))


def _phi(d):
    c = np.empty(d.shape + (2, 2), d.dtype)
    c[..., 0, 0] = c[..., 1, 1] = d.dtype.type(1) if d.dtype != object else Fraction(1)
    c[..., 1, 0] = c[..., 0, 0] * 0
    c[..., 0, 1] = d
    return _kron(c, _num(np.eye(3), d.dtype == object))


def _mm(a, b):
    """Batched matrix product that also works on object arrays."""
    return np.matmul(a, b) if a.dtype != object else np.einsum("...ij,...jk->...ik", a, b)


def _t(a):
    return np.swapaxes(a, -1, -2)


def dense_reference(t, y, R, qc, z, P0=None, m0=None, exact=False):
    """Exact posterior at the times ``z`` of the batch GP with the WNOA kernel.

    The kernel of the process started at ``tref`` with zero state is ``kron(c(u, v), Qc)``
    (:func:`_iwp_coef`); the state at ``tref`` is given a flat prior (universal kriging: the
    limit ``P0^-1 -> 0`` of a Gaussian prior; placed at ``tref = min(t0, z)``, which gives
    the same posterior and likelihood as at ``t0``). A proper prior ``x(t0) ~ N(m0, P0)`` is
    the same flat prior and one more observation ``m0 = x(t0) + e``, ``e ~ N(0, P0)`` (an
    identical posterior and marginal likelihood; done this way, the large prior variances
    never cancel against the small posterior ones). Measurements ``y_k = p(t_k) + n_k``,
    ``n_k ~ N(0, R_k)``. Computed in ``np.longdouble``, or with ``exact`` in rational
    arithmetic (no rounding at all: slow, for small problems).

    Returns mean (M, 6), marginal covariances (M, 6, 6), ``Cov(x(z_i), x(z_i+1))``
    (M-1, 6, 6) and the log marginal likelihood (diffuse: the density of the data with the
    initial state integrated over Lebesgue measure).
    """
    proper = P0 is not None
    t, z, qc = (_num(a, exact) for a in (t, z, qc))
    n, M = t.shape[0], z.shape[0]
    tref = t[0] if proper else min(t[0], z.min())
    u, w = t - tref, z - tref
    # observed components of the knot states: positions, then the whole first state (prior)
    idx = (6 * np.arange(n)[:, None] + np.arange(3)).ravel()
    noise = [_num(r, exact) for r in R]
    obs = np.ravel(y)
    if proper:
        idx = np.concatenate([idx, np.arange(6)])
        noise.append(_num(P0, exact))
        obs = np.concatenate([obs, np.ravel(m0)])
    yv = _num(obs, exact)
    m = idx.size
    k_xx = _kron(_iwp_coef(u[:, None], u[None, :]), qc).transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)
    k_zx = _kron(_iwp_coef(w[:, None], u[None, :]), qc).transpose(0, 2, 1, 3).reshape(6 * M, 6 * n)
    k_zz = _kron(_iwp_coef(w, w), qc)  # (M, 6, 6)
    k_zz1 = _kron(_iwp_coef(w[:-1], w[1:]), qc)  # (M-1, 6, 6)
    G = k_xx[np.ix_(idx, idx)].copy()
    i0 = 0
    for c in noise:
        k = c.shape[0]
        G[i0:i0 + k, i0:i0 + k] += c
        i0 += k
    kzy = k_zx[:, idx]  # (6M, m)
    F = _phi(u).reshape(6 * n, 6)[idx]  # observations of the flat initial state
    a_z = _phi(w)
    sol, logdet_g = _solve_spd(G, np.concatenate([yv[:, None], F, kzy.T], axis=1))
    g_y, g_f, g_k = sol[:, 0], sol[:, 1:7], sol[:, 7:]
    b = F.T @ g_y
    U = a_z - (kzy @ g_f).reshape(M, 6, 6)
    rhs = np.concatenate([b[:, None], U.transpose(2, 0, 1).reshape(6, 6 * M)], axis=1)
    sol_m, logdet_m = _solve_spd(F.T @ g_f, rhs)
    beta, mi_ut = sol_m[:, 0], sol_m[:, 1:].reshape(6, M, 6).transpose(1, 0, 2)
    mean = (a_z @ beta) + (kzy @ (g_y - g_f @ beta)).reshape(M, 6)
    kz = kzy.reshape(M, 6, m)
    gk = g_k.reshape(m, M, 6).transpose(1, 0, 2)
    cov = k_zz - _mm(kz, gk) + _mm(U, mi_ut)
    cross = k_zz1 - _mm(kz[:-1], gk[1:]) + _mm(U[:-1], mi_ut[1:])
    log2pi = float(_log(2 * _num(math.pi, exact)))
    loglik = (-0.5 * float(yv @ g_y - b @ beta) - 0.5 * float(logdet_g)
              - 0.5 * float(logdet_m) - (0.5 * m - 3) * log2pi)
    return mean.astype(float), cov.astype(float), cross.astype(float), loglik


def kalman_loglik(t, y, R, qc, P0=None, m0=None, scale=None):
    """Prediction-error decomposition of a Kalman filter (diffuse: exact start at t1);
    ``scale``: a multiplier of Qc per interval."""
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    qc = as_qc(qc)
    scale = np.ones(len(t) - 1) if scale is None else np.asarray(scale, dtype=float)

    def q(k):  # interval k, from t_k to t_k+1
        d = t[k + 1] - t[k]
        return scale[k] * np.kron([[d**3 / 3, d**2 / 2], [d**2 / 2, d]], qc)

    def phi(d):
        return np.kron([[1.0, d], [0.0, 1.0]], np.eye(3))

    ll = 0.0
    if P0 is None:
        d = t[1] - t[0]
        Qi, F = np.linalg.inv(q(0)), phi(d)
        r0i, r1i = np.linalg.inv(R[0]), np.linalg.inv(R[1])
        J00 = F.T @ Qi @ F + H.T @ r0i @ H
        J01 = -F.T @ Qi
        J11 = Qi + H.T @ r1i @ H
        h0, h1 = H.T @ r0i @ y[0], H.T @ r1i @ y[1]
        Jm = J11 - J01.T @ np.linalg.solve(J00, J01)
        P = np.linalg.inv(Jm)
        m = P @ (h1 - J01.T @ np.linalg.solve(J00, h0))
        ll = -3.0 * math.log(d)
        start = 2
    else:
        m, P = np.asarray(m0, float), np.asarray(P0, float)
        start = 0
    for k in range(start, len(t)):
        if k > 0:
            d = t[k] - t[k - 1]
            m = phi(d) @ m
            P = phi(d) @ P @ phi(d).T + q(k - 1)
        e = y[k] - m[:3]
        S = P[:3, :3] + R[k]
        ll += stats.multivariate_normal(np.zeros(3), S).logpdf(e)
        K = np.linalg.solve(S, P[:3]).T
        m = m + K @ e
        P = P - K @ S @ K.T
    return ll


# --------------------------------------------------------------------------------------------
# Random problems and simulation from the prior
# --------------------------------------------------------------------------------------------


def random_spd(rng, n, scale, cond=100.0):
    """``n`` random full SPD 3x3 matrices with eigenvalues in ``scale * [1/cond, 1]``."""
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    ev = scale * np.exp(rng.uniform(-math.log(cond), 0.0, size=(n, 3)))
    a = (q * ev[:, None, :]) @ np.swapaxes(q, 1, 2)
    return 0.5 * (a + np.swapaxes(a, 1, 2))  # exactly symmetric


def random_times(rng, n, t0=0.0, gap_prob=0.15, dt_max=1.0, gap_factor=(3.0, 10.0)):
    """Increasing times: steps uniform in [0.05, dt_max] s, a fraction of them stretched into
    gaps (by a factor uniform in ``gap_factor``)."""
    dt = rng.uniform(0.05, dt_max, n - 1)
    big = rng.random(n - 1) < gap_prob
    dt[big] *= rng.uniform(*gap_factor, big.sum())
    return t0 + np.concatenate([[0.0], np.cumsum(dt)])


def random_qc(rng, kind, lo=-3.0, hi=1.0):
    scale = 10.0 ** rng.uniform(lo, hi)
    if kind == "scalar":
        return scale
    if kind == "diag":
        return scale * np.exp(rng.uniform(-1, 1, 3))
    return random_spd(rng, 1, scale, cond=10.0)[0]


def random_problem(rng, n, qc_kind="full", t0=0.0):
    """A random track for the comparison with the extended-precision dense reference.

    The dense kernel solution loses about ``log10(max prior variance / min posterior
    variance)`` digits; in these ranges (Qc 1e-3 to 1e-1 m^2/s^3, measurement standard
    deviations 0.6 mm to 10 cm, steps up to 0.6 s, gaps up to 4.8 s, N <= 60, which covers
    RTS tracks) the ``longdouble`` reference is good to better than 1e-10. Wider ranges are
    checked against the exact rational reference on small problems.
    """
    t = random_times(rng, n, t0, dt_max=0.6, gap_factor=(2.0, 8.0))
    R = random_spd(rng, n, 10.0 ** rng.uniform(-5, -2), cond=30.0)
    y = np.cumsum(rng.normal(size=(n, 3)), axis=0) + rng.normal(size=3) * 10
    return t, y, R, random_qc(rng, qc_kind, -3.0, -1.0)


def extreme_problem(rng, n, t0=1.668e9):
    """Small, badly conditioned tracks: gaps up to 15 s, Qc up to 10 m^2/s^3, measurement
    standard deviations from 0.1 mm to 30 cm, strongly anisotropic covariances."""
    t = random_times(rng, n, t0, gap_prob=0.4, gap_factor=(5.0, 15.0))
    R = random_spd(rng, n, 10.0 ** rng.uniform(-6, -1), cond=100.0)
    y = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    return t, y, R, as_qc(random_qc(rng, "full", -3.0, 1.0))


def random_prior(rng, y0):
    """A proper prior on the first state: standard deviations ~ 1 cm to 1 m (m, m/s)."""
    a = rng.normal(size=(6, 6)) * 10.0 ** rng.uniform(-2, 0)
    P0 = a @ a.T + 1e-5 * np.eye(6)
    P0 = 0.5 * (P0 + P0.T)  # exactly symmetric
    m0 = np.concatenate([y0, np.zeros(3)]) + np.sqrt(np.diag(P0)) * rng.normal(size=6)
    return P0, m0


def simulate_prior(rng, times, qc, x0):
    """States ``[p, v]`` (len(times), 6) of the WNOA process through ``x0`` at ``times[0]``."""
    lq = np.linalg.cholesky(as_qc(qc))
    d = np.diff(times)
    # kron(chol(A(d)), chol(Qc)) is a Cholesky factor of Q(d) = kron(A(d), Qc)
    la = np.zeros((d.size, 2, 2))
    la[:, 0, 0] = np.sqrt(d**3 / 3)
    la[:, 1, 0] = (d**2 / 2) / la[:, 0, 0]
    la[:, 1, 1] = np.sqrt(d - la[:, 1, 0] ** 2)
    e = rng.normal(size=(d.size, 2, 3))
    w = np.einsum("nab,nbj->naj", la, e) @ lq.T  # (n-1, 2, 3): [w_p, w_v] per step
    v = x0[3:] + np.concatenate([np.zeros((1, 3)), np.cumsum(w[:, 1], axis=0)])
    p = x0[:3] + np.concatenate([np.zeros((1, 3)), np.cumsum(d[:, None] * v[:-1] + w[:, 0], 0)])
    return np.concatenate([p, v], axis=1)


def measure(rng, p, R):
    return p + np.einsum("nij,nj->ni", np.linalg.cholesky(R), rng.normal(size=p.shape))


def rel_err(a, b):
    """max |a - b| / max |b|."""
    return float(np.abs(np.asarray(a) - b).max() / np.abs(b).max())


def cov_err(a, b, var_left, var_right):
    """max |a_ij - b_ij| / sqrt(var_left_i var_right_j) (relative to the standard deviations)."""
    scale = np.sqrt(var_left[..., :, None] * var_right[..., None, :])
    return float(np.max(np.abs(np.asarray(a) - b) / scale))


def diag(c):
    return np.diagonal(c, axis1=-2, axis2=-1)


# --------------------------------------------------------------------------------------------
# Exactness against the dense batch GP
# --------------------------------------------------------------------------------------------


def check_against_dense(seed, n, prior, qc_kind, epoch, n_query=12):
    rng = np.random.default_rng(seed)
    t0 = 1.668e9 + rng.uniform(0, 1e5) if epoch else rng.uniform(-10, 10)
    t, y, R, qc = random_problem(rng, n, qc_kind, t0)
    P0 = m0 = None
    kw = {}
    if prior == "proper":
        P0, m0 = random_prior(rng, y[0])
        kw = {"initial_state_cov": P0, "initial_state_mean": m0}
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, **kw)
    tq = np.concatenate([rng.uniform(t[0], t[-1], n_query), t[rng.integers(0, n, 2)]])
    z = np.concatenate([t, tq])
    mean, cov, cross, ll = dense_reference(t, y, R, as_qc(qc), z, P0, m0)
    mk, ck = mean[:n], cov[:n]
    # knots: means (positions and velocities separately), covariances, lag-one covariances
    assert rel_err(gp.mean[:, :3], mk[:, :3]) < TOL
    assert rel_err(gp.mean[:, 3:], mk[:, 3:]) < TOL
    assert cov_err(gp.cov, ck, diag(ck), diag(ck)) < TOL
    assert cov_err(gp.cross_cov, cross[: n - 1], diag(ck[:-1]), diag(ck[1:])) < TOL
    # queries
    res = gp.query(tq, with_velocity=True)
    assert rel_err(res.position, mean[n:, :3]) < TOL
    assert rel_err(res.velocity, mean[n:, 3:]) < TOL
    cq = cov[n:]
    assert cov_err(res.state_cov, cq, diag(cq), diag(cq)) < TOL
    assert cov_err(res.position_cov, cq[:, :3, :3], diag(cq)[:, :3], diag(cq)[:, :3]) < TOL
    assert cov_err(res.velocity_cov, cq[:, 3:, 3:], diag(cq)[:, 3:], diag(cq)[:, 3:]) < TOL
    # marginal likelihood
    assert gp.log_likelihood == pytest.approx(ll, rel=TOL, abs=TOL)
    lm = log_marginal_likelihood((t, y, R), qc, **kw)
    assert lm == pytest.approx(ll, rel=TOL, abs=TOL)
    return gp


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**63 - 1),
    n=st.integers(2, 60),
    prior=st.sampled_from(["diffuse", "proper"]),
    qc_kind=st.sampled_from(["scalar", "diag", "full"]),
    epoch=st.booleans(),
)
def test_exact_against_dense_batch_gp(seed, n, prior, qc_kind, epoch):
    check_against_dense(seed, n, prior, qc_kind, epoch)


@pytest.mark.parametrize("n", [2, 3, 4, 5, 8, 31, 32, 33, 60])
@pytest.mark.parametrize("prior", ["diffuse", "proper"])
def test_exact_against_dense_every_reduction_shape(n, prior):
    """Odd and even counts at every level of the cyclic reduction (2^k, 2^k +- 1)."""
    check_against_dense(1000 + n, n, prior, "full", epoch=n % 2 == 0, n_query=6)


@pytest.mark.parametrize(("n", "prior", "seed"),
                         [(2, "diffuse", 1), (3, "proper", 2), (5, "diffuse", 3), (6, "proper", 4)])
def test_exact_against_rational_arithmetic_on_ill_conditioned_tracks(n, prior, seed):
    """The dense reference in exact rational arithmetic (no rounding at all) on tracks far
    from the ranges above: the code loses no more than a few digits to the conditioning."""
    rng = np.random.default_rng(seed)
    t, y, R, qc = extreme_problem(rng, n)
    P0 = m0 = None
    kw = {}
    if prior == "proper":
        P0, m0 = random_prior(rng, y[0])
        kw = {"initial_state_cov": P0, "initial_state_mean": m0}
        tq = rng.uniform(t[0], t[-1] + 5, 4)
    else:
        tq = rng.uniform(t[0] - 5, t[-1] + 5, 4)
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, **kw)
    mean, cov, cross, ll = dense_reference(t, y, R, qc, np.concatenate([t, tq]), P0, m0,
                                           exact=True)
    ck = cov[:n]
    assert rel_err(gp.mean[:, :3], mean[:n, :3]) < 1e-12
    assert rel_err(gp.mean[:, 3:], mean[:n, 3:]) < 1e-12
    assert cov_err(gp.cov, ck, diag(ck), diag(ck)) < 1e-12
    assert cov_err(gp.cross_cov, cross[: n - 1], diag(ck[:-1]), diag(ck[1:])) < 1e-12
    res = gp.query(tq, with_velocity=True, allow_gaps=True)
    cq = cov[n:]
    assert rel_err(res.position, mean[n:, :3]) < 1e-12
    assert cov_err(res.state_cov, cq, diag(cq), diag(cq)) < 1e-12
    assert gp.log_likelihood == pytest.approx(ll, rel=1e-12, abs=1e-9)


def test_extrapolation_is_the_dense_prediction():
    """With allow_gaps, queries before/after the track and across gaps are the exact GP."""
    rng = np.random.default_rng(5)
    n = 25
    t, y, R, qc = random_problem(rng, n, "full", 100.0)
    gp = fit_track((t, y, R), qc=qc, max_gap_s=0.5)
    tq = np.sort(np.concatenate([t[0] - rng.uniform(0, 20, 4), t[-1] + rng.uniform(0, 20, 4),
                                 rng.uniform(t[0], t[-1], 8)]))
    res = gp.query(tq, with_velocity=True, allow_gaps=True)
    mean, cov, _, _ = dense_reference(t, y, R, as_qc(qc), tq)
    assert rel_err(res.position, mean[:, :3]) < TOL
    assert rel_err(res.velocity, mean[:, 3:]) < TOL
    assert cov_err(res.state_cov, cov, diag(cov), diag(cov)) < TOL
    assert np.array_equal(res.extrapolated, (tq < t[0]) | (tq > t[-1]))
    assert np.all(res.across_gap[res.extrapolated])


@pytest.mark.parametrize("prior", ["diffuse", "proper"])
def test_likelihood_is_the_kalman_prediction_error_decomposition(prior):
    rng = np.random.default_rng(11)
    for n in (2, 3, 17, 40):
        t, y, R, qc = random_problem(rng, n, "full")
        kw, P0, m0 = {}, None, None
        if prior == "proper":
            P0, m0 = random_prior(rng, y[0])
            kw = {"initial_state_cov": P0, "initial_state_mean": m0}
        ll = log_marginal_likelihood((t, y, R), qc, **kw)
        assert ll == pytest.approx(kalman_loglik(t, y, R, qc, P0, m0), rel=1e-8, abs=1e-8)


def dense_chain_posterior(t, y, R, qc, scale, extra):
    """Posterior of the states at the knots ``t`` and at the ``extra`` times (no measurement
    there), from the dense information matrix of the Markov chain: increments
    ``x_j+1 - Phi x_j ~ N(0, Q(dt, s Qc))`` with ``s`` the scale of the knot interval holding
    them, diffuse first state, measurements at the knots. Returns (times, mean, cov)."""
    times = np.unique(np.concatenate([t, extra]))
    n = times.size
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    J = np.zeros((6 * n, 6 * n))
    h = np.zeros(6 * n)
    for j in range(n - 1):
        d = times[j + 1] - times[j]
        k = int(np.clip(np.searchsorted(t, times[j], side="right") - 1, 0, len(t) - 2))
        A = np.zeros((6, 6 * n))
        A[:, 6 * j:6 * j + 6] = -wnoa_phi(d)
        A[:, 6 * j + 6:6 * j + 12] = np.eye(6)
        J += A.T @ np.linalg.inv(wnoa_q(d, scale[k] * as_qc(qc))) @ A
    for i, tk in enumerate(t):
        j = int(np.searchsorted(times, tk))
        ri = np.linalg.inv(R[i])
        J[6 * j:6 * j + 6, 6 * j:6 * j + 6] += H.T @ ri @ H
        h[6 * j:6 * j + 6] += H.T @ ri @ y[i]
    cov = np.linalg.inv(J)
    mean = cov @ h
    blocks = np.array([cov[6 * j:6 * j + 6, 6 * j:6 * j + 6] for j in range(n)])
    return times, mean.reshape(n, 6), blocks


def test_a_qc_scaled_per_interval_is_the_dense_chain_and_the_kalman_likelihood():
    """``qc_scale``: interval k has Qc_k = s_k Qc. Knots, queries between knots and beyond the
    ends against the dense information form of the chain; the marginal likelihood against a
    Kalman filter with the same per-interval process noise; scales of 1 change nothing."""
    rng = np.random.default_rng(41)
    t, y, R, qc = random_problem(rng, 12, "diag")
    y = y - y[0]  # centred: the dense float64 solve keeps its digits
    scale = np.exp(rng.uniform(-4.0, 3.0, t.size - 1))
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, qc_scale=scale)
    tq = np.sort(np.concatenate([
        rng.uniform(t[0], t[-1], 15), [t[0] - 0.7, t[-1] + 0.4]]))
    times, mean, cov = dense_chain_posterior(t, y, R, qc, scale, tq)
    at = np.searchsorted(times, t)
    np.testing.assert_allclose(gp.mean, mean[at], rtol=0, atol=1e-7 * np.abs(mean).max())
    assert cov_err(gp.cov, cov[at], diag(cov[at]), diag(cov[at])) < 1e-7
    res = gp.query(tq, with_velocity=True, allow_gaps=True)
    aq = np.searchsorted(times, tq)
    np.testing.assert_allclose(res.position, mean[aq, :3], rtol=0, atol=1e-7 * np.abs(mean).max())
    assert cov_err(res.state_cov, cov[aq], diag(cov[aq]), diag(cov[aq])) < 1e-7
    ll = log_marginal_likelihood((t, y, R), qc)
    assert gp.log_likelihood == pytest.approx(kalman_loglik(t, y, R, qc, scale=scale), rel=1e-8)
    assert gp.log_likelihood != pytest.approx(ll, rel=1e-3)
    same = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, qc_scale=np.ones(t.size - 1))
    plain = fit_track((t, y, R), qc=qc, max_gap_s=np.inf)
    np.testing.assert_allclose(same.cov, plain.cov, rtol=1e-14, atol=0)
    assert same.log_likelihood == pytest.approx(plain.log_likelihood, rel=1e-14)
    with pytest.raises(InputError, match="qc_scale"):
        fit_track((t, y, R), qc=qc, qc_scale=np.ones(t.size))
    with pytest.raises(InputError, match="qc_scale needs a given qc"):
        fit_track((t, y, R), qc_scale=np.ones(t.size - 1))


@pytest.mark.parametrize("prior", ["diffuse", "proper"])
def test_held_out_measurements_are_knots_without_weight(prior):
    """``held_out`` (cross-validation): with one Qc, the posterior at a held-out knot and the
    joint covariance of two of them are the prediction of the fit without those measurements,
    and so is the log likelihood; with a Qc per interval, the dense chain with those
    measurements given (almost) no weight."""
    from rtsgt.interpolation.cross import gp_cross_covariance

    rng = np.random.default_rng(43)
    t, y, R, qc = random_problem(rng, 30, "diag")
    y = y - y[0]
    held = np.zeros(t.size, bool)
    held[[3, 4, 5, 17, 29]] = True  # a window, a point, the last one (extrapolated)
    kw = {}
    if prior == "proper":
        P0, m0 = random_prior(rng, y[0])
        kw = {"initial_state_cov": P0, "initial_state_mean": m0}
    else:
        held[0] = True  # the first one too (before the track of the others)
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, held_out=held, **kw)
    ref = fit_track((t[~held], y[~held], R[~held]), qc=qc, max_gap_s=np.inf, **kw) \
        if prior == "diffuse" else None
    if ref is not None:
        q = ref.query(t[held], with_velocity=True, allow_gaps=True)
        np.testing.assert_allclose(gp.mean[held], np.column_stack([q.position, q.velocity]),
                                   rtol=0, atol=1e-9 * np.abs(y).max())
        assert cov_err(gp.cov[held], q.state_cov, diag(q.state_cov), diag(q.state_cov)) < 1e-8
        c = gp_cross_covariance(ref, t[[3, 4]], t[[4, 5]])  # consecutive held-out knots
        assert cov_err(gp.cross_cov[[3, 4]], c, diag(gp.cov[[3, 4]]), diag(gp.cov[[4, 5]])) < 1e-8
        assert gp.log_likelihood == pytest.approx(ref.log_likelihood, rel=1e-10)
    else:
        # the first knot keeps its measurement: the proper prior is on the same state
        assert gp.log_likelihood == pytest.approx(
            kalman_loglik(t[~held], y[~held], R[~held], qc, P0=kw["initial_state_cov"],
                          m0=kw["initial_state_mean"]), rel=1e-8)
    scale = np.exp(rng.uniform(-3.0, 2.0, t.size - 1))
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, qc_scale=scale, held_out=held, **kw)
    if prior == "diffuse":
        R_w = np.where(held[:, None, None], 1e12 * R, R)
        _, mean, cov = dense_chain_posterior(t, y, R_w, qc, scale, np.empty(0))
        np.testing.assert_allclose(gp.mean, mean, rtol=0, atol=1e-6 * np.abs(mean).max())
        assert cov_err(gp.cov, cov, diag(cov), diag(cov)) < 1e-6
    with pytest.raises(InputError, match="held_out as a boolean mask"):
        fit_track((t, y, R), qc=qc, held_out=np.zeros(t.size))
    with pytest.raises(InputError, match="at least 2 measurements left"):
        fit_track((t, y, R), qc=qc, held_out=np.arange(t.size) > 0)


def test_diffuse_is_the_limit_of_a_wide_proper_prior():
    rng = np.random.default_rng(2)
    t, y, R, qc = random_problem(rng, 20, "diag")
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf)
    wide = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, initial_state_cov=1e10 * np.eye(6))
    assert gp.diffuse_prior and not wide.diffuse_prior
    np.testing.assert_allclose(wide.mean, gp.mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(wide.cov, gp.cov, rtol=0, atol=1e-8 * np.abs(gp.cov).max())


def test_wnoa_building_blocks():
    qc = random_spd(np.random.default_rng(0), 1, 0.3)[0]
    for d in (1e-3, 0.4, 7.0):
        Q = wnoa_q(d, qc)
        np.testing.assert_allclose(wnoa_q_inv(d, qc) @ Q, np.eye(6), atol=1e-9)
        c = _iwp_coef(d, d).astype(float)
        np.testing.assert_allclose(Q, np.kron(c, qc), rtol=1e-14)
        np.testing.assert_allclose(wnoa_phi(d) @ wnoa_phi(-d), np.eye(6), atol=1e-15)
    # Chapman-Kolmogorov: Q(a + b) = Phi(b) Q(a) Phi(b)^T + Q(b)
    a, b = 0.7, 1.9
    np.testing.assert_allclose(
        wnoa_q(a + b, qc), wnoa_phi(b) @ wnoa_q(a, qc) @ wnoa_phi(b).T + wnoa_q(b, qc),
        rtol=1e-12,
    )
    assert wnoa_q(np.array([0.1, 0.2]), 1.0).shape == (2, 6, 6)
    np.testing.assert_array_equal(as_qc(2.0), 2 * np.eye(3))
    np.testing.assert_array_equal(as_qc([1, 2, 3]), np.diag([1.0, 2, 3]))


# --------------------------------------------------------------------------------------------
# Queries: knots, order, chunks, equivariance
# --------------------------------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 40))
def test_query_on_a_knot_is_the_knot_posterior(seed, n):
    rng = np.random.default_rng(seed)
    t, y, R, qc = random_problem(rng, n, "full", 1.668e9)
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf)
    idx = rng.permutation(n)
    res = gp.query(t[idx], with_velocity=True)
    np.testing.assert_array_equal(res.position, gp.mean[idx, :3])
    np.testing.assert_array_equal(res.velocity, gp.mean[idx, 3:])
    np.testing.assert_array_equal(res.state_cov, gp.cov[idx])
    np.testing.assert_array_equal(res.nearest_measurement_dt, 0.0)
    assert not res.across_gap.any()
    # and the interpolation formula is continuous at the knots
    eps = 1e-7 * np.minimum(np.diff(t)[np.clip(idx, 0, n - 2)], 1.0)
    near = gp.query(np.clip(t[idx] + eps, None, t[-1]), with_velocity=True)
    np.testing.assert_allclose(near.position, res.position, atol=1e-6)
    np.testing.assert_allclose(near.state_cov, res.state_cov, atol=1e-6 * np.abs(gp.cov).max())


def test_query_order_chunks_and_velocity_flag():
    rng = np.random.default_rng(3)
    t, y, R, qc = random_problem(rng, 50, "diag")
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf)
    tq = rng.uniform(t[0], t[-1], 70_000)  # more than one chunk of 65536
    full = gp.query(tq, with_velocity=True)
    part = gp.query(tq[:1000], with_velocity=True)
    tail = gp.query(tq[-1000:])
    np.testing.assert_allclose(full.position[:1000], part.position, rtol=0, atol=0)
    np.testing.assert_allclose(full.state_cov[:1000], part.state_cov, rtol=0, atol=0)
    np.testing.assert_allclose(full.position_cov[-1000:], tail.position_cov, rtol=0, atol=0)
    assert tail.velocity is None and tail.state_cov is None
    assert len(full) == 70_000
    np.testing.assert_allclose(full.position_sigma,
                               np.sqrt(np.trace(full.position_cov, axis1=1, axis2=2) / 3))
    # symmetric positive definite everywhere
    assert np.all(np.linalg.eigvalsh(full.state_cov[::97]) > 0)
    np.testing.assert_array_equal(full.state_cov, np.swapaxes(full.state_cov, 1, 2))
    # read-only results
    with pytest.raises(ValueError):
        full.position[0, 0] = 0.0
    # a scalar query
    one = gp.query(float(tq[0]))
    np.testing.assert_array_equal(one.position[0], full.position[0])


def test_translation_equivariance_and_prism_track_input():
    rng = np.random.default_rng(4)
    t, y, R, qc = random_problem(rng, 30, "scalar", 1.668e9)
    shift = np.array([1234.5, -987.25, 42.0])
    a = fit_track((t, y, R), qc=qc)
    b = fit_track(PrismTrack(t=t, xyz=y + shift, cov=R, prism="7", frame="site"), qc=qc)
    assert b.prism == "7" and b.frame == "site"
    np.testing.assert_allclose(b.mean[:, :3], a.mean[:, :3] + shift, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9, atol=0)
    assert b.log_likelihood == pytest.approx(a.log_likelihood, rel=1e-12)


# --------------------------------------------------------------------------------------------
# Statistical truth: coverage and Qc estimation on tracks simulated from the prior
# --------------------------------------------------------------------------------------------


def test_coverage_of_95_percent_ellipsoids_on_tracks_from_the_prior():
    rng = np.random.default_rng(20240101)
    d2_pos, d2_state, kinds = [], [], []
    for _ in range(120):
        n = int(rng.integers(20, 60))
        t = random_times(rng, n, 1.668e9)
        qc = random_qc(rng, ["scalar", "diag", "full"][int(rng.integers(3))])
        R = random_spd(rng, n, 10.0 ** rng.uniform(-6, -3))
        tq = np.concatenate([rng.uniform(t[0], t[-1], 36), t[rng.integers(0, n, 2)],
                             t[0] - rng.uniform(0, 2, 1), t[-1] + rng.uniform(0, 2, 1)])
        allt, inv = np.unique(np.concatenate([t, tq]), return_inverse=True)
        x0 = np.concatenate([rng.normal(size=3) * 100, rng.normal(size=3)])
        x = simulate_prior(rng, allt, qc, x0)
        y = measure(rng, x[inv[:n], :3], R)
        gp = fit_track((t, y, R), qc=qc, max_gap_s=3.0)
        res = gp.query(tq, with_velocity=True, allow_gaps=True)
        e = x[inv[n:]] - np.concatenate([res.position, res.velocity], axis=1)
        d2_pos.append(np.einsum("qi,qi->q", e[:, :3], np.linalg.solve(res.position_cov,
                                                                      e[:, :3, None])[..., 0]))
        d2_state.append(np.einsum("qi,qi->q", e, np.linalg.solve(res.state_cov,
                                                                 e[..., None])[..., 0]))
        kinds.append(np.where(res.extrapolated, 2, np.where(res.across_gap, 1, 0)))
    d2_pos, d2_state, kinds = map(np.concatenate, (d2_pos, d2_state, kinds))
    assert d2_pos.size == 120 * 40
    cover = np.mean(d2_pos <= CHI2_95_3)
    assert abs(cover - 0.95) < 0.02, cover
    assert abs(np.mean(d2_state <= CHI2_95_6) - 0.95) < 0.02
    # the Mahalanobis distances follow chi-square(3) (mean 3), also inside supported spans
    assert abs(np.mean(d2_pos) - 3.0) < 0.2
    inside = kinds == 0
    assert inside.sum() > 2500
    assert abs(np.mean(d2_pos[inside] <= CHI2_95_3) - 0.95) < 0.02
    assert stats.kstest(d2_pos, stats.chi2(3).cdf).pvalue > 1e-3


@pytest.mark.parametrize("q_true", [1e-3, 0.05, 2.0])
def test_fitted_isotropic_qc_recovers_the_truth(q_true):
    rng = np.random.default_rng(int(q_true * 1e4))
    n = 400
    t = 1.668e9 + np.cumsum(rng.uniform(0.3, 0.5, n))
    R = random_spd(rng, n, 9e-6, cond=10)  # ~3 mm
    x = simulate_prior(rng, t, q_true, np.array([10.0, -5, 2, 0.5, 0.1, 0]))
    y = measure(rng, x[:, :3], R)
    qc, ll, info = fit_qc((t, y, R))
    assert info.converged and not info.at_bound and info.mode == "isotropic"
    np.testing.assert_allclose(qc, qc[0, 0] * np.eye(3))
    assert abs(qc[0, 0] / q_true - 1) < 0.2, qc[0, 0]
    # a maximum of the likelihood
    assert ll == pytest.approx(log_marginal_likelihood((t, y, R), qc), rel=1e-12)
    for f in (0.9, 1.1):
        assert log_marginal_likelihood((t, y, R), f * qc) < ll
    # fit_track(fit_qc=True) and fit_track(qc=None) give the same Qc and report it
    gp = fit_track((t, y, R), fit_qc=True)
    assert gp.qc_fit is not None and gp.qc_fit.converged
    np.testing.assert_allclose(gp.qc, qc, rtol=1e-12)
    np.testing.assert_allclose(fit_track((t, y, R)).qc, qc, rtol=1e-12)
    assert gp.log_likelihood == pytest.approx(ll, rel=1e-12)
    # a given qc is used as it is, without a fit report
    assert fit_track((t, y, R), qc=q_true).qc_fit is None


def test_fitted_per_axis_qc_recovers_the_truth():
    rng = np.random.default_rng(77)
    q_true = np.array([0.01, 0.2, 3.0])
    n = 600
    t = np.cumsum(rng.uniform(0.3, 0.5, n))
    R = random_spd(rng, n, 4e-6, cond=10)
    x = simulate_prior(rng, t, q_true, np.zeros(6))
    y = measure(rng, x[:, :3], R)
    gp = fit_track((t, y, R), fit_qc=True, qc_mode="per-axis")
    assert gp.qc_fit.mode == "per-axis" and gp.qc_fit.converged
    np.testing.assert_array_less(np.abs(np.diag(gp.qc) / q_true - 1), 0.2)
    assert np.count_nonzero(gp.qc - np.diag(np.diag(gp.qc))) == 0
    # starting from a guess gives the same estimate
    qc2, _, _ = fit_qc((t, y, R), mode="per-axis", qc0=1.0)
    np.testing.assert_allclose(np.diag(qc2), np.diag(gp.qc), rtol=1e-2)


def test_static_prism_gives_a_tiny_qc_and_a_bound_is_reported():
    rng = np.random.default_rng(8)
    n = 100
    t = np.arange(n) * 0.4
    R = random_spd(rng, n, 1e-6, cond=5)
    y = measure(rng, np.zeros((n, 3)) + [1.0, 2.0, 3.0], R)
    gp = fit_track((t, y, R))
    # no acceleration: the estimate is below anything a moving prism shows (~1e-3 and up)
    assert gp.qc[0, 0] < 1e-8
    assert np.all(np.isfinite(gp.cov))
    np.testing.assert_allclose(gp.position, [[1.0, 2.0, 3.0]] * n, atol=1e-3)
    # when the search interval excludes it, the estimate sits on the bound and says so
    qc, _, info = fit_qc((t, y, R), bounds=(1e-4, 1e2))
    assert info.at_bound and not info.converged
    assert "bound" in info.message
    assert qc[0, 0] == pytest.approx(1e-4, rel=1e-3)
    _, _, info = fit_qc((t, y, R), mode="per-axis", bounds=(1e-4, 1e2))
    assert info.at_bound and not info.converged


# --------------------------------------------------------------------------------------------
# Extrapolation and long gaps
# --------------------------------------------------------------------------------------------


def gap_track():
    rng = np.random.default_rng(9)
    t = np.array([0.0, 0.4, 0.8, 1.2, 5.2, 5.6, 6.0, 9.0, 9.4])  # gaps of 4.0 s and 3.0 s
    R = random_spd(rng, t.size, 1e-5)
    y = np.cumsum(rng.normal(size=(t.size, 3)) * 0.1, axis=0)
    return fit_track((t, y, R), qc=0.1, max_gap_s=3.0)


def test_queries_beyond_the_ends_or_across_long_gaps_are_refused():
    gp = gap_track()
    with pytest.raises(ExtrapolationError, match=r"before the first measurement \(t = 0.0 s\)"):
        gp.query([0.2, -0.1])
    with pytest.raises(ExtrapolationError, match="after the last measurement"):
        gp.query([9.5])
    with pytest.raises(ExtrapolationError, match=r"inside a gap of 4.000 s .*max_gap_s = 3.0"):
        gp.query([3.0])
    with pytest.raises(ExtrapolationError, match=r"\(2 of 3 queries unsupported\)"):
        gp.query([3.0, 9.2, 100.0])
    # an ExtrapolationError is an InputError (bad query) as well
    with pytest.raises(InputError, match="allow_gaps=True"):
        gp.query([20.0])


def test_supported_and_flags():
    gp = gap_track()
    tq = np.array([-0.1, 0.0, 0.5, 1.2, 1.3, 5.1, 5.2, 7.0, 9.0, 9.4, 9.5])
    expected = np.array([0, 1, 1, 1, 0, 0, 1, 1, 1, 1, 0], bool)  # 3.0 s gap: not > max_gap_s
    np.testing.assert_array_equal(gp.supported(tq), expected)
    res = gp.query(tq, allow_gaps=True)
    np.testing.assert_array_equal(res.across_gap, ~expected)
    np.testing.assert_array_equal(res.extrapolated, (tq < 0) | (tq > 9.4))
    np.testing.assert_allclose(res.nearest_measurement_dt,
                               [0.1, 0, 0.1, 0, 0.1, 0.1, 0, 1.0, 0, 0, 0.1], atol=1e-12)
    ok = gp.query(tq[expected])
    assert not ok.across_gap.any() and not ok.extrapolated.any()
    # sigma grows away from the data: mid-gap > near the knots, and with the extrapolation
    sig = gp.query([1.2, 3.2, 5.2], allow_gaps=True).position_sigma
    assert sig[1] > 5 * max(sig[0], sig[2])
    ext = gp.query([9.4, 10.4, 12.4], allow_gaps=True).position_sigma
    assert ext[0] < ext[1] < ext[2]


def test_max_gap_is_configurable():
    gp = gap_track()
    wide = fit_track((gp.t, gp.position, gp.position_cov), qc=0.1, max_gap_s=5.0)
    assert wide.supported([3.0])[0] and not gp.supported([3.0])[0]
    assert not wide.query([3.0]).across_gap[0]


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


def good_track(n=6):
    rng = np.random.default_rng(10)
    return np.arange(n) * 0.5, rng.normal(size=(n, 3)), random_spd(rng, n, 1e-4)


def test_too_few_measurements():
    t, y, R = good_track(1)
    with pytest.raises(InputError, match="at least 2 measurements.*got 1"):
        fit_track((t, y, R), qc=1.0)
    with pytest.raises(InputError, match="got 0"):
        fit_track((t[:0], y[:0], R[:0]), qc=1.0)
    with pytest.raises(InputError, match="got 1"):
        fit_qc((t, y, R))


@pytest.mark.parametrize(
    ("times", "what"), [([0.0, 0.5, 0.5, 1.0], "duplicated"), ([0.0, 0.5, 0.4, 1.0], "unsorted")]
)
def test_times_not_strictly_increasing(times, what):
    _, y, R = good_track(4)
    msg = rf"{what} times: measurement 2 \(t = 0.[45] s\) after measurement 1 \(t = 0.5 s\)"
    with pytest.raises(InputError, match=msg):
        fit_track((np.array(times), y, R), qc=1.0)


@settings(max_examples=40, deadline=None)
@given(
    which=st.sampled_from(["t", "xyz", "cov"]),
    index=st.integers(0, 5),
    value=st.sampled_from([np.nan, np.inf, -np.inf]),
)
def test_non_finite_values_name_the_measurement(which, index, value):
    t, y, R = good_track(6)
    arrays = {"t": t.copy(), "xyz": y.copy(), "cov": R.copy()}
    a = arrays[which]
    a.reshape(6, -1)[index, -1] = value
    with pytest.raises(InputError, match=rf"NaN or inf in {which} of measurement {index}\b"):
        fit_track((arrays["t"], arrays["xyz"], arrays["cov"]), qc=1.0)


def test_covariances_must_be_symmetric_positive_definite():
    t, y, R = good_track(6)
    bad = R.copy()
    bad[3, 0, 1] += 1e-5
    with pytest.raises(InputError, match=r"symmetric covariance.*measurement 3 \(t = 1.5 s\)"):
        fit_track((t, y, bad), qc=1.0)
    bad = R.copy()
    bad[4] = np.diag([1e-4, 1e-4, -1e-6])
    with pytest.raises(InputError, match=r"positive definite covariance.*measurement 4"):
        fit_track((t, y, bad), qc=1.0)
    bad[4] = np.diag([1e-4, 1e-4, 0.0])
    with pytest.raises(InputError, match="positive definite"):
        fit_track((t, y, bad), qc=1.0)


def test_bad_shapes_qc_and_options():
    t, y, R = good_track(6)
    with pytest.raises(InputError, match=r"xyz of shape \(6, 3\)"):
        fit_track((t, y[:, :2], R), qc=1.0)
    with pytest.raises(InputError, match=r"cov of shape \(6, 3, 3\)"):
        fit_track((t, y, R[:5]), qc=1.0)
    with pytest.raises(InputError, match="PrismTrack or a tuple"):
        fit_track(np.zeros((6, 4)), qc=1.0)
    for qc in (-1.0, 0.0, np.nan, [1.0, -1.0, 1.0], [[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]],
               np.ones((2, 2))):
        with pytest.raises(InputError, match="qc"):
            fit_track((t, y, R), qc=qc)
    with pytest.raises(InputError, match="max_gap_s"):
        fit_track((t, y, R), qc=1.0, max_gap_s=0.0)
    with pytest.raises(InputError, match="qc_mode"):
        fit_track((t, y, R), fit_qc=True, qc_mode="full")
    with pytest.raises(InputError, match="initial_state_mean needs initial_state_cov"):
        fit_track((t, y, R), qc=1.0, initial_state_mean=np.zeros(6))
    with pytest.raises(InputError, match="positive definite initial_state_cov"):
        fit_track((t, y, R), qc=1.0, initial_state_cov=-np.eye(6))
    with pytest.raises(InputError, match="bounds"):
        fit_qc((t, y, R), bounds=(1.0, 0.1))


def test_bad_query_times():
    gp: GPTrack = fit_track(good_track(6), qc=1.0)
    with pytest.raises(InputError, match=r"finite query times, got nan at index 1"):
        gp.query([0.1, np.nan])
    with pytest.raises(InputError, match=r"shape \(Q,\)"):
        gp.query(np.zeros((2, 2)))
    with pytest.raises(InputError, match="before the first measurement"):
        gp.query([-1.0])
    with pytest.raises(InputError, match="after the last measurement"):
        gp.query([1e9])
    assert len(gp.query(np.empty(0))) == 0


# --------------------------------------------------------------------------------------------
# The real excerpt (Vaidis et al. 2023, 2022-11-10): modules 1 and 2, then the GP
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real_run():
    from rtsgt.io.deployment import load_deployment
    from rtsgt.pipeline import run_pipeline

    data, opts = load_deployment(EXAMPLE)
    return run_pipeline(data, opts)


def test_real_excerpt_through_modules_1_2_and_the_gp(real_run):
    from rtsgt.interpolation.prisms import gp_covariance, query_grid

    res = real_run
    reports = res.computation.filter_reports
    assert {f"module1_station{s}" for s in "123"} <= set(reports)
    for s in "123":
        rep = reports[f"module1_station{s}"]
        assert rep.n_in > 200 and rep.n_removed < 0.05 * rep.n_in  # already through module 1
    iv = res.intervals
    assert iv.shape[1] == 2 and np.all(iv[:, 1] - iv[:, 0] >= 2.0)
    grid = query_grid(iv, 5.0)
    assert grid.size > 400
    for pid, tr in res.computation.tracks.items():
        # the marginal-likelihood Qc of this issue, on the white noise the pipeline feeds the GP
        gp = fit_track((tr.t, tr.xyz, gp_covariance(tr, "white")), fit_qc=True, max_gap_s=3.0)
        q = gp.qc[0, 0]
        assert np.isfinite(q) and 1e-5 < q < 1.0, q
        assert gp.qc_fit.converged and not gp.qc_fit.at_bound
        # the pipeline's own GP (whichever Qc it chose) is sane too
        assert np.all(np.isfinite(res.computation.gps[pid].qc)) and res.computation.gps[pid].qc[0, 0] > 0
        # every 5 Hz time of the common intervals is supported (module 2 kept the brackets)
        assert np.all(gp.supported(grid))
        sigma = gp.query(grid).position_sigma
        assert 0.5e-3 < np.median(sigma) < 5e-3, np.median(sigma)  # a few mm
        knots = np.sqrt(np.trace(gp.position_cov, axis1=1, axis2=2) / 3)
        assert np.median(knots) < np.median(sigma)
        # sigma grows across a gap: largest mid-gap, refused there without allow_gaps
        dt = np.diff(gp.t)
        k = int(np.argmax(dt))
        assert dt[k] > 10.0
        frac = np.array([0.0, 0.1, 0.25, 0.5])
        s_gap = gp.query(gp.t[k] + frac * dt[k], allow_gaps=True).position_sigma
        assert np.all(np.diff(s_gap) > 0) and s_gap[-1] > 50 * np.median(sigma)
        with pytest.raises(ExtrapolationError):
            gp.query([gp.t[k] + 0.5 * dt[k]])
        short = np.flatnonzero((dt > 1.0) & (dt <= 3.0))
        mid = gp.query(gp.t[short] + 0.5 * dt[short]).position_sigma
        assert np.all(mid > np.maximum(knots[short], knots[short + 1]))
