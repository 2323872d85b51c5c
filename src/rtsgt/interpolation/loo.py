"""``Qc`` by leave-one-out cross-validation: each measurement predicted from all the others
(the interpolation the ground truth performs), from the smoothed posterior without refitting.

Owns :class:`LooScorer` (a track checked once, any number of candidate ``Qc`` and per-interval
scales scored in one solve), :func:`maximise` (L-BFGS-B with the forward-difference steps
scored together) and :func:`fit_qc_loo` (isotropic, then per axis). Why not the marginal
likelihood, the predictive's closed form and the search: docs/interpolation.md#qc-by-leave-one-out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from rtsgt.errors import InputError
from rtsgt.interpolation.gp import (
    DEFAULT_MAX_GAP_S,
    QC_BOUNDS,
    as_qc,
    check_scale,
    posteriors,
    prepare_track,
    track_arrays,
)

__all__ = ["FD_STEP", "LooInfo", "LooScorer", "fit_qc_loo", "loo_predictive", "loo_score",
           "maximise"]


@dataclass(frozen=True)
class LooInfo:
    """Result of :func:`fit_qc_loo`.

    Attributes
    ----------
    qc : float or ndarray (3, 3)
        The isotropic power spectral density (float), or the diagonal ``Qc`` (per axis),
        m^2/s^3.
    log_predictive : float
        ``L_LOO`` at ``qc`` (sum over the knots used).
    n_used : int
        Knots scored (interior, neighbours within ``max_gap_s``).
    nees_mean : float
        Mean of ``(y_k - mu_-k)^T (Sigma_-k + R_k)^-1 (y_k - mu_-k) / 3`` at ``qc``.
    """

    qc: float
    log_predictive: float
    n_used: int
    nees_mean: float


def _interior(t: np.ndarray, max_gap_s: float) -> np.ndarray:
    dt = np.diff(t)
    ok = np.zeros(t.shape[0], dtype=bool)
    ok[1:-1] = (dt[:-1] <= max_gap_s) & (dt[1:] <= max_gap_s)
    return ok


class LooScorer:
    """Leave-one-out predictive of one track under any ``Qc``: the track is validated and its
    knots chosen once, each candidate costs one smoother pass (the search's unit of work).

    Parameters
    ----------
    track : (t, xyz, cov)
        Times (N,) s, positions (N, 3) m, measurement covariances (N, 3, 3) m^2.
    max_gap_s : float
        Knots with a neighbour farther than this are not scored.
    prior : {"wnoa", "wnoj"}
        The motion prior (:mod:`rtsgt.interpolation.gp`).

    Attributes
    ----------
    used : ndarray of bool, shape (N,)
        The knots scored.
    """

    def __init__(self, track, max_gap_s: float = DEFAULT_MAX_GAP_S, prior: str = "wnoa"):
        self._data = prepare_track(track, prior=prior)
        t = self._data.t
        self.used = _interior(t, max_gap_s)
        R = track_arrays(track)[2][self.used]
        self._R = 0.5 * (R + np.swapaxes(R, 1, 2))
        self._logdet_r = np.linalg.slogdet(self._R)[1]
        # the smallest variance of each R_k: the floor of A_k's eigenvalues below
        self._floor = 1e-12 * np.linalg.eigvalsh(self._R)[:, :1]

    @property
    def n_used(self) -> int:
        """Knots scored."""
        return int(self.used.sum())

    def _factor(self, qcs, scales):
        """``e_k = y_k - m_k`` (K, U, 3) and ``A_k = R_k - P_k`` (K, U, 3, 3) at the scored
        knots (module docstring) under K candidates, as ``A_k`` 's eigen-decomposition
        ``(w, V)`` or its Cholesky factor ``(L, None)``."""
        mean, S = posteriors(self._data, [as_qc(q) for q in qcs],
                              [check_scale(self._data, s) for s in scales])
        e = self._data.y[self.used] - mean[:, self.used, :3]
        A = self._R - S[:, self.used]
        A = 0.5 * (A + np.swapaxes(A, -1, -2))
        try:
            return e, np.linalg.cholesky(A), None
        except np.linalg.LinAlgError:
            # a Qc so large that the others say almost nothing about y_k (P_k -> R_k): floor
            # A_k's eigenvalues at a tiny fraction of R_k's (a huge but finite predictive)
            w, V = np.linalg.eigh(A)
            return e, np.maximum(w, self._floor), V

    def predictive(self, qc, qc_scale=None) -> tuple[np.ndarray, np.ndarray]:
        """``y_k - mu_-k`` (U, 3), m, and ``Sigma_-k + R_k`` (U, 3, 3), m^2, at the scored
        knots, under ``qc`` (a scalar: ``qc I``) times ``qc_scale`` per interval."""
        e, f, V = (None if a is None else a[0] for a in self._factor([qc], [qc_scale]))
        if V is None:
            a_inv = np.linalg.inv(f)
            a_inv = np.swapaxes(a_inv, 1, 2) @ a_inv
        else:
            a_inv = np.einsum("nij,nj,nkj->nik", V, 1.0 / f, V)
        ra = self._R @ a_inv
        return np.einsum("nij,nj->ni", ra, e), ra @ self._R

    def scores(self, qcs, scales=None) -> list[tuple[float, float, int]]:
        """``(L_LOO, mean NEES / 3, knots scored)`` under each of the candidates ``qcs``
        (each times its entry of ``scales``, None: 1), computed together."""
        scales = [None] * len(qcs) if scales is None else scales
        e, f, V = self._factor(qcs, scales)
        if V is None:
            z = np.linalg.solve(f, e[..., None])[..., 0]
            nees = np.einsum("kni,kni->kn", z, z)
            logdet_a = 2.0 * np.log(np.diagonal(f, axis1=-2, axis2=-1)).sum(axis=-1)
        else:
            z = np.einsum("knji,knj->kni", V, e)
            nees = np.einsum("kni,kni->kn", z * z, 1.0 / f)
            logdet_a = np.log(f).sum(axis=-1)
        ll = -0.5 * np.sum(nees + 2.0 * self._logdet_r - logdet_a + 3.0 * np.log(2.0 * np.pi),
                           axis=-1)
        return [(float(ll[k]), float(nees[k].mean() / 3.0), int(e.shape[1]))
                for k in range(len(qcs))]

    def __call__(self, qc, qc_scale=None) -> tuple[float, float, int]:
        """``(L_LOO, mean NEES / 3, knots scored)`` under ``qc`` times ``qc_scale``."""
        return self.scores([qc], [qc_scale])[0]


#: Step of the forward differences of :func:`maximise`, in a log-PSD or a log-scale.
FD_STEP = 1e-3


def maximise(values, x0: np.ndarray, lo: float, hi: float):
    """Maximise a score over parameters in ``[lo, hi]`` by L-BFGS-B (:mod:`scipy.optimize`).

    The gradient is taken by forward differences of :data:`FD_STEP` (backward where the
    step would leave the upper bound, as scipy's own finite differences are taken), and the
    point and its steps are scored together: ``values(points)`` returns the scores of a list
    of points (:meth:`LooScorer.scores` solves them as one system).

    Returns
    -------
    scipy.optimize.OptimizeResult
        Of the minimisation of the negated score (``x``, ``fun = -score``, ``nit``...).
    """
    def value_and_gradient(x: np.ndarray) -> tuple[float, np.ndarray]:
        step = np.where(x + FD_STEP > hi, -FD_STEP, FD_STEP)
        points = [x] + [x + np.eye(x.size)[i] * step[i] for i in range(x.size)]
        f = -np.asarray(values(points), dtype=float)
        dx = np.array([points[i + 1][i] - x[i] for i in range(x.size)])
        return float(f[0]), (f[1:] - f[0]) / dx

    return minimize(value_and_gradient, np.asarray(x0, dtype=float), jac=True,
                    method="L-BFGS-B", bounds=[(lo, hi)] * len(x0))


def loo_predictive(track, qc, *, max_gap_s: float = DEFAULT_MAX_GAP_S, qc_scale=None,
                   prior: str = "wnoa"):
    """Leave-one-out predictive of every interior measurement (:class:`LooScorer`).

    Parameters
    ----------
    track : (t, xyz, cov)
        Times (N,) s, positions (N, 3) m, measurement covariances (N, 3, 3) m^2.
    qc : float or array_like (3, 3)
        Power spectral density, m^2/s^3 (a scalar means ``qc I``).
    max_gap_s : float
        Knots with a neighbour farther than this are not scored.
    qc_scale : array_like, shape (N-1,), optional
        Per-interval multiplier of ``qc`` (:func:`rtsgt.interpolation.gp.fit_track`).
    prior : {"wnoa", "wnoj"}
        The motion prior (:mod:`rtsgt.interpolation.gp`).

    Returns
    -------
    used : ndarray of bool, shape (N,)
    residual : ndarray, shape (U, 3)
        ``y_k - mu_-k`` at the used knots, m.
    cov : ndarray, shape (U, 3, 3)
        ``Sigma_-k + R_k``, m^2.
    """
    scorer = LooScorer(track, max_gap_s, prior)
    return (scorer.used, *scorer.predictive(qc, qc_scale))


def loo_score(track, qc, max_gap_s: float = DEFAULT_MAX_GAP_S, qc_scale=None,
              prior: str = "wnoa") -> tuple[float, float, int]:
    """Leave-one-out score of ``qc`` (and ``qc_scale``, under ``prior``,
    :class:`LooScorer`).

    Returns
    -------
    log_predictive : float
        ``L_LOO``: the sum of the log predictive densities of the scored measurements.
    nees_per_dof : float
        Mean of their normalised squared residuals over 3.
    n_used : int
        Measurements scored.
    """
    return LooScorer(track, max_gap_s, prior)(qc, qc_scale)


def fit_qc_loo(
    track, *, mode: str = "isotropic", max_gap_s: float = DEFAULT_MAX_GAP_S,
    bounds: tuple[float, float] = QC_BOUNDS, xatol: float = 0.02, prior: str = "wnoa",
) -> LooInfo:
    """``Qc`` maximising the leave-one-out log predictive density.

    Parameters
    ----------
    track : (t, xyz, cov)
        As for :func:`rtsgt.interpolation.gp.fit_track`.
    mode : {"isotropic", "per-axis"}
        ``Qc = q I``, or a diagonal ``Qc`` with one ``q`` per world axis.
    max_gap_s : float
        Knots next to a longer gap are not scored.
    bounds : (float, float)
        Search interval for each ``q``, m^2/s^3.
    xatol : float
        Tolerance on the isotropic ``log q`` (0.02: 2 % on ``q``, well inside its statistical
        uncertainty); the per-axis search then stops where L-BFGS-B's defaults say.
    prior : {"wnoa", "wnoj"}
        The motion prior whose ``Qc`` is fitted (m^2/s^3 for WNOA, m^2/s^5 for WNOJ).

    Returns
    -------
    LooInfo
        ``qc`` is a float (isotropic) or a diagonal (3, 3) array (per axis).

    Raises
    ------
    InputError
        Fewer than 5 interior knots to score, an unknown mode, or a track that
        :func:`rtsgt.interpolation.gp.fit_track` refuses.
    """
    if mode not in ("isotropic", "per-axis"):
        raise InputError(f"Expected mode 'isotropic' or 'per-axis', got {mode!r}")
    score = LooScorer(track, max_gap_s, prior)
    if score.n_used < 5:
        raise InputError(
            f"Expected at least 5 measurements with neighbours within max_gap_s = {max_gap_s} s "
            f"to fit Qc by leave-one-out, got {score.n_used}"
        )
    lo, hi = (float(np.log(b)) for b in bounds)
    res = minimize_scalar(lambda lq: -score(np.exp(lq))[0],
                          bounds=(lo, hi), method="bounded", options={"xatol": xatol})
    qc: float | np.ndarray = float(np.exp(res.x))
    if mode == "per-axis":
        # the search stays inside the bounds: a static track drives q towards 0, and a q far
        # below the floor (4e-20 was seen) makes the track's information matrix singular
        best = maximise(
            lambda points: [v[0] for v in score.scores(
                [np.diag(np.exp(np.clip(p, lo, hi))) for p in points])],
            np.full(3, float(res.x)), lo, hi)
        qc = np.diag(np.exp(np.clip(best.x, lo, hi)))
    ll, nees, n = score(qc)
    return LooInfo(qc, ll, n, nees)
