r"""Trajectory error metrics: evo's APE and RPE, and the uncertainty-aware ones.

APE, RPE and their statistics as evo (docs/evaluation.md#ape-and-rpe); the pose error in the
left-perturbation convention, NEES and its consistency test (docs/evaluation.md#nees); the
split test of errors shared by the deployment
(docs/evaluation.md#errors-shared-by-the-deployment); the noise floor and the relative pose
covariance (docs/evaluation.md#relative-pose-covariance). Imports only numpy, scipy and rtsgt.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import hat, log_so3
from rtsgt.stats import integrated_autocorrelation_time

#: Names of the statistics, in evo's order.
STATISTICS = ("rmse", "mean", "median", "std", "min", "max")

#: Units accepted for the RPE delta: metres of path, seconds, frames.
DELTA_UNITS = ("m", "s", "f")

#: Relative tolerance of the consecutive RPE pair selection: a path (time) since the last
#: selected pose reaches ``delta`` when it is at least ``delta * (1 - RPE_TIE_RTOL)``
#: (:func:`rpe_pairs`). Far above the rounding of a sum of steps (a few units in the last place
#: per step), far below any meaningful distance.
RPE_TIE_RTOL = 1e-9


def error_statistics(errors: ArrayLike) -> dict[str, float]:
    """evo's statistics of errors (N,): dict of :data:`STATISTICS` (rmse, mean, median, std ddof 0,
    min, max), Python floats.
    """
    e = np.asarray(errors, dtype=float)
    if e.ndim != 1 or e.size == 0:
        raise ValueError(f"Expected a non-empty 1-D error array, got shape {e.shape}")
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
    }


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    return np.linalg.norm(log_so3(R), axis=-1)


def _full_error(R_E: np.ndarray, t_E: np.ndarray) -> np.ndarray:
    """``||E - I_4||_F`` for E = [[R_E, t_E], [0, 1]]."""
    dR = R_E - np.eye(3)
    return np.sqrt(np.einsum("...ij,...ij->...", dR, dR) + np.einsum("...i,...i->...", t_E, t_E))


def ape_errors(
    R_gt: ArrayLike, t_gt: ArrayLike, R_est: ArrayLike, t_est: ArrayLike
) -> dict[str, np.ndarray]:
    """Per-pose APE with evo's definitions, ``E = P^-1 Q``, from ``R_world_body`` (N, 3, 3) and
    ``t_world_body`` (N, 3) m of the ground truth and the aligned estimate: dict of (N,)
    ``translation`` (m), ``rotation_rad``, ``full`` (``||E - I||_F``).
    """
    R_gt = np.asarray(R_gt, dtype=float)
    R_est = np.asarray(R_est, dtype=float)
    d = np.asarray(t_gt, dtype=float) - np.asarray(t_est, dtype=float)
    RestT = np.swapaxes(R_est, -1, -2)
    R_E = RestT @ R_gt
    t_E = np.einsum("...ij,...j->...i", RestT, d)
    return {
        "translation": np.linalg.norm(-d, axis=-1),
        "rotation_rad": _rotation_angle(R_E),
        "full": _full_error(R_E, t_E),
    }


def relative_poses(
    R: np.ndarray, t: np.ndarray, pairs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``T_i^-1 T_j`` for index pairs: rotation (K, 3, 3), translation (K, 3) in frame i."""
    i, j = pairs[:, 0], pairs[:, 1]
    RiT = np.swapaxes(R[i], -1, -2)
    return RiT @ R[j], np.einsum("kab,kb->ka", RiT, t[j] - t[i])


def rpe_errors(
    R_gt: ArrayLike, t_gt: ArrayLike, R_est: ArrayLike, t_est: ArrayLike, pairs: ArrayLike
) -> dict[str, np.ndarray]:
    """Per-pair relative pose errors with evo's definitions.

    ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (Sturm et al. 2012); returns ``translation`` (m),
    ``rotation_rad`` and ``full`` arrays of shape (K,).
    """
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    RQ, tQ = relative_poses(np.asarray(R_gt, float), np.asarray(t_gt, float), pairs)
    RP, tP = relative_poses(np.asarray(R_est, float), np.asarray(t_est, float), pairs)
    RQT = np.swapaxes(RQ, -1, -2)
    R_E = RQT @ RP
    t_E = np.einsum("kab,kb->ka", RQT, tP - tQ)
    return {
        "translation": np.linalg.norm(t_E, axis=-1),
        "rotation_rad": _rotation_angle(R_E),
        "full": _full_error(R_E, t_E),
    }


def _consecutive_by_path(inc: np.ndarray, reach: float) -> np.ndarray:
    """Start indices of consecutive segments whose path reaches ``reach`` metres.

    The path since the last selected pose is summed sequentially from zero, as evo's
    ``filter_pairs_by_path`` does; ``reach`` is ``delta`` less the tie tolerance.
    """
    n = inc.size + 1
    ids = [0]
    start = 0
    w = 64
    while start < n - 1:
        stop = min(start + w, n - 1)
        cs = np.cumsum(inc[start:stop])
        hit = np.flatnonzero(cs >= reach)
        if hit.size:
            start = start + int(hit[0]) + 1
            ids.append(start)
            w = max(64, 2 * (int(hit[0]) + 1))
        elif stop >= n - 1:
            break
        else:
            w *= 2
    return np.asarray(ids, dtype=int)


def _all_pairs_nearest(D: np.ndarray, delta: float, tol: float) -> np.ndarray:
    """For every i, the first j > i minimising ``|(D_j - D_i) - delta|``, kept if within tol.

    ``D`` is non-decreasing (accumulated path or time). Vectorised version of evo's
    ``filter_pairs_by_path(all_pairs=True)`` loop (argmin, first occurrence on ties).
    """
    n = D.size
    if n < 2:
        return np.zeros((0, 2), dtype=int)
    i = np.arange(n - 1)
    k = np.searchsorted(D, D[i] + delta, side="left")
    cand = k[:, None] + np.arange(-2, 2)[None, :]
    cand = np.clip(cand, (i + 1)[:, None], n - 1)
    val = np.abs((D[cand] - D[i][:, None]) - delta)
    best = np.argmin(val, axis=1)
    # among equal values the smallest index wins (argmin on clipped, sorted candidates)
    j = cand[np.arange(n - 1), best]
    vmin = val[np.arange(n - 1), best]
    # a plateau of equal D values extends the tie to the left: take its first index > i
    j = np.maximum(np.searchsorted(D, D[j], side="left"), i + 1)
    keep = vmin <= tol
    return np.stack([i[keep], j[keep]], axis=1)


def rpe_pairs(
    position: ArrayLike,
    t: ArrayLike | None,
    delta: float,
    delta_unit: str = "f",
    *,
    all_pairs: bool = False,
    rel_tol: float = 0.1,
) -> np.ndarray:
    """Index pairs (K, 2) for the RPE, selected as evo does (docs/evaluation.md#ape-and-rpe).

    ``position`` (N, 3) of the trajectory the pairs come from, ``t`` (N,) s for ``delta_unit="s"``;
    ``delta`` in frames ("f"), metres of path ("m") or seconds ("s"). Consecutive non-overlapping
    pairs (evo's default; a separation reaches ``delta`` within :data:`RPE_TIE_RTOL`, plus
    16 ulp of the stamps for times, so exact ties give the same pairs on every machine), or with
    ``all_pairs`` the j > i closest to ``delta`` within ``rel_tol * delta`` (evo's arithmetic).
    """
    p = np.asarray(position, dtype=float)
    n = p.shape[0]
    if delta_unit not in DELTA_UNITS:
        raise ValueError(f"Expected a delta unit in {DELTA_UNITS}, got {delta_unit!r}")
    if not np.isfinite(delta) or delta <= 0:
        raise ValueError(f"Expected a positive delta, got {delta}")
    if delta_unit == "f":
        if float(delta) != int(delta):
            raise ValueError(f"Expected an integer delta for unit 'f' (frames), got {delta}")
        d = int(delta)
        if all_pairs:
            i = np.arange(max(n - d, 0))
            return np.stack([i, i + d], axis=1)
        ids = np.arange(0, n, d)
        return np.stack([ids[:-1], ids[1:]], axis=1)
    if delta_unit == "m":
        inc = np.linalg.norm(p[:-1] - p[1:], axis=1)
        if all_pairs:
            D = np.concatenate([[0.0], np.cumsum(inc)])
            return _all_pairs_nearest(D, float(delta), float(delta) * rel_tol)
        ids = _consecutive_by_path(inc, float(delta) * (1.0 - RPE_TIE_RTOL))
        return np.stack([ids[:-1], ids[1:]], axis=1)
    if t is None:
        raise ValueError("Expected times for a delta in seconds")
    tt = np.asarray(t, dtype=float)
    if all_pairs:
        return _all_pairs_nearest(tt, float(delta), float(delta) * rel_tol)
    if n == 0:
        return np.zeros((0, 2), dtype=int)
    reach = float(delta) * (1.0 - RPE_TIE_RTOL) - 16.0 * float(np.spacing(np.max(np.abs(tt))))
    ids = [0]
    while True:
        k = int(np.searchsorted(tt, tt[ids[-1]] + reach, side="left"))
        if k <= ids[-1]:
            k = ids[-1] + 1
        if k >= n:
            break
        ids.append(k)
    ids = np.asarray(ids, dtype=int)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def pose_error(R_gt: ArrayLike, t_gt: ArrayLike, R_est: ArrayLike, t_est: ArrayLike) -> np.ndarray:
    """Pose error ``(t_est - t_gt, log(R_est R_gt^T))`` in the world frame, shape (N, 6).

    The left perturbation of :func:`rtsgt.geometry.transform.perturbation` of the estimate
    about the ground truth, ordered (x, y, z, rx, ry, rz); m and rad.
    """
    R_gt = np.asarray(R_gt, dtype=float)
    R_est = np.asarray(R_est, dtype=float)
    dtheta = log_so3(R_est @ np.swapaxes(R_gt, -1, -2))
    return np.concatenate([np.asarray(t_est, float) - np.asarray(t_gt, float), dtheta], axis=-1)


def relative_pose_error_vector(
    R_gt: ArrayLike, t_gt: ArrayLike, R_est: ArrayLike, t_est: ArrayLike, pairs: ArrayLike
) -> np.ndarray:
    """Error of the relative pose ``P_i^-1 P_j`` about ``Q_i^-1 Q_j``, shape (K, 6), frame i.

    Same convention as :func:`pose_error`, applied to the relative poses (coordinates of the
    ground-truth body frame at i): ``(t_P,ij - t_Q,ij, log(R_P,ij R_Q,ij^T))``.
    """
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    RQ, tQ = relative_poses(np.asarray(R_gt, float), np.asarray(t_gt, float), pairs)
    RP, tP = relative_poses(np.asarray(R_est, float), np.asarray(t_est, float), pairs)
    return pose_error(RQ, tQ, RP, tP)


def relative_pose_covariance(
    R_i: ArrayLike,
    t_i: ArrayLike,
    t_j: ArrayLike,
    cov_i: ArrayLike,
    cov_j: ArrayLike,
    cross_ij: ArrayLike | None = None,
) -> np.ndarray:
    r"""First-order covariance (K, 6, 6), in frame i, of ``T_ij = T_i^-1 T_j`` from ``R_i`` (K, 3, 3),
    ``t_i``, ``t_j`` (K, 3) m, world-frame left-perturbation covariances ``cov_i``, ``cov_j``
    (K, 6, 6) and ``cross_ij = Cov(xi_i, xi_j)`` (None: independent);
    docs/evaluation.md#relative-pose-covariance.
    """
    R_i = np.asarray(R_i, dtype=float)
    K = R_i.shape[0]
    RiT = np.swapaxes(R_i, -1, -2)
    B = np.zeros((K, 6, 6))
    B[:, :3, :3] = RiT
    B[:, 3:, 3:] = RiT
    A = np.zeros((K, 6, 6))
    A[:, :3, :3] = -np.eye(3)
    A[:, :3, 3:] = hat(np.asarray(t_j, float) - np.asarray(t_i, float))
    A[:, 3:, 3:] = -np.eye(3)
    Ji = B @ A
    Jj = B
    JiT = np.swapaxes(Ji, -1, -2)
    JjT = np.swapaxes(Jj, -1, -2)
    cov = Ji @ np.asarray(cov_i, float) @ JiT + Jj @ np.asarray(cov_j, float) @ JjT
    if cross_ij is not None:
        X = Ji @ np.asarray(cross_ij, float) @ JjT
        cov = cov + X + np.swapaxes(X, -1, -2)
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def chain_cross_covariance(cov: ArrayLike, cross_next: ArrayLike, pairs: ArrayLike) -> np.ndarray:
    r"""``Cov(xi_i, xi_j)`` (K, 6, 6) for ``pairs`` (K, 2), i < j, from ``cov`` (M, 6, 6) and
    consecutive ``cross_next`` (M - 1, 6, 6) by the Markov chain rule
    (docs/evaluation.md#relative-pose-covariance); NaN across an unknown (NaN) link.
    """
    P = np.asarray(cov, dtype=float)
    C = np.asarray(cross_next, dtype=float)
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    i, j = pairs[:, 0], pairs[:, 1]
    if np.any(j <= i):
        raise ValueError("Expected pairs with i < j")
    out = C[i].copy()
    span = j - i
    if span.size and span.max() > 1:
        # G_k = P_k^-1 C_k (Cholesky-free solve; falls back to the pseudo-inverse)
        try:
            G = np.linalg.solve(P[:-1], C)
        except np.linalg.LinAlgError:
            G = np.linalg.pinv(P[:-1]) @ C
        for s in range(1, int(span.max())):
            active = span > s
            out[active] = out[active] @ G[i[active] + s]
    return out


def no_pair_reason(position: np.ndarray, t: np.ndarray, delta: float, unit: str) -> str:
    """Why :func:`rpe_pairs` found no pair among the poses at ``position`` (N, 3) m and ``t``
    (N,) s, and what to change."""
    n = t.shape[0]
    if unit == "m":
        path = float(np.sum(np.linalg.norm(np.diff(position, axis=0), axis=1)))
        have, want = f"{path:.3g} m of path", f"{delta:g} m"
    elif unit == "s":
        span = float(t[-1] - t[0]) if n else 0.0
        have, want = f"{span:.3g} s", f"{delta:g} s"
    else:
        have, want = f"{n} associated poses", f"{int(delta)} frames"
    return (
        f"no pose pair {want} apart: the {n} associated poses span {have}; "
        "use a smaller RPE delta"
    )


def squared_mahalanobis(e: ArrayLike, S: ArrayLike) -> np.ndarray:
    """``e_k^T S_k^-1 e_k`` (N,) for ``e`` (N, d), ``S`` (N, d, d) by Cholesky; ValueError naming the
    first ``S_k`` that is not positive definite.
    """
    e = np.asarray(e, dtype=float)
    S = np.asarray(S, dtype=float)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(0.5 * (S + np.swapaxes(S, -1, -2)))
        k = int(np.argmin(eig.min(axis=-1)))
        raise ValueError(
            f"Expected positive definite covariances, got one with eigenvalue "
            f"{eig[k].min():.3g} at index {k}"
        ) from None
    z = np.linalg.solve(L, e[..., None])[..., 0]
    return np.einsum("...i,...i->...", z, z)


@dataclass(frozen=True)
class NeesResult:
    """NEES of N poses against chi-square(dof), with a consistency verdict (docs/evaluation.md#nees).

    ``values`` (N,); ``mean`` (``dof`` when consistent); ``fraction_inside_95`` below
    ``quantile_95 = chi2.ppf(0.95, dof)``; ``n``, ``n_eff = n / tau``; two-sided ``1 - alpha``
    ``mean_interval`` and ``fraction_interval``; ``consistent``: both inside, or with ``split``
    (a :class:`SplitVerdict`) its verdict.
    """

    values: np.ndarray
    dof: int
    mean: float
    fraction_inside_95: float
    quantile_95: float
    n: int
    n_eff: float
    mean_interval: tuple[float, float]
    fraction_interval: tuple[float, float]
    consistent: bool
    alpha: float = 0.05
    split: SplitVerdict | None = None

    @property
    def mean_ok(self) -> bool:
        return self.mean_interval[0] <= self.mean <= self.mean_interval[1]

    @property
    def fraction_ok(self) -> bool:
        return self.fraction_interval[0] <= self.fraction_inside_95 <= self.fraction_interval[1]

    def to_dict(self) -> dict:
        """JSON-ready: ``mean, dof, fraction_inside_95, consistent`` and the test details."""
        return {
            "mean": float(self.mean),
            "dof": int(self.dof),
            "fraction_inside_95": float(self.fraction_inside_95),
            "consistent": bool(self.consistent),
            "n": int(self.n),
            "n_eff": float(self.n_eff),
            "mean_interval": [float(v) for v in self.mean_interval],
            "fraction_interval": [float(v) for v in self.fraction_interval],
            "quantile_95": float(self.quantile_95),
            "alpha": float(self.alpha),
            "verdict": ("shared and varying parts tested apart (shared factor of the ground "
                        "truth)" if self.split is not None else
                        "autocorrelation of the NEES series (no shared factor)"),
            **({} if self.split is None else {"split": self.split.to_dict()}),
        }


def nees_test(e: np.ndarray, S: np.ndarray, dof: int, what: str, t: np.ndarray) -> NeesResult:
    """NEES of errors ``e`` (N, dof) with covariances ``S`` (N, dof, dof) and its consistency
    test (:func:`nees_consistency`); a covariance that is not positive definite is an
    InputError naming ``what`` and the times ``t``."""
    try:
        d2 = squared_mahalanobis(e, S)
    except ValueError as exc:
        raise InputError(f"Cannot compute the {what} NEES: {exc} (t = {t})") from None
    return nees_consistency(d2, dof)


def nees_consistency(
    nees: ArrayLike, dof: int, *, alpha: float = 0.05, correlated: bool = True
) -> NeesResult:
    r"""Chi-square consistency test (:class:`NeesResult`) of per-pose NEES values (N,) with ``dof``
    3 or 6, at significance ``alpha`` per two-sided test: the mean and the share inside the 95 %
    region, with effective sample sizes from the autocorrelation (``correlated=False``: the
    textbook independent test); docs/evaluation.md#nees.
    """
    v = np.asarray(nees, dtype=float)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"Expected a non-empty 1-D NEES array, got shape {v.shape}")
    n = v.size
    q95 = float(stats.chi2.ppf(0.95, dof))
    inside = v <= q95
    mean = float(v.mean())
    frac = float(inside.mean())
    tau = integrated_autocorrelation_time(v) if correlated else 1.0
    tau_i = integrated_autocorrelation_time(inside.astype(float)) if correlated else 1.0
    n_eff = n / tau
    lo = float(stats.chi2.ppf(alpha / 2, n_eff * dof) / n_eff)
    hi = float(stats.chi2.ppf(1 - alpha / 2, n_eff * dof) / n_eff)
    m = max(1, int(round(n / tau_i)))
    flo = float(stats.binom.ppf(alpha / 2, m, 0.95) / m)
    fhi = float(stats.binom.ppf(1 - alpha / 2, m, 0.95) / m)
    ok = (lo <= mean <= hi) and (flo <= frac <= fhi)
    return NeesResult(v, int(dof), mean, frac, q95, n, n_eff, (lo, hi), (flo, fhi), bool(ok), alpha)


def noise_floor(cov_pos: ArrayLike) -> float:
    """Ground-truth noise floor ``sqrt(mean_k tr Sigma_k)`` of ``cov_pos`` (N, d, d), m or rad
    (docs/evaluation.md#noise-floor).
    """
    c = np.asarray(cov_pos, dtype=float)
    return float(np.sqrt(np.mean(np.trace(c, axis1=-2, axis2=-1))))


def remove_floor(rmse: float, floor: float) -> float:
    """``sqrt(max(rmse^2 - floor^2, 0))``: the rmse with the ground truth's own noise removed."""
    return float(np.sqrt(max(rmse * rmse - floor * floor, 0.0)))



# --------------------------------------------------------------------------------------------
# errors shared by the deployment: the split test
# --------------------------------------------------------------------------------------------

#: Alignment methods and the number of parameters each absorbs (:func:`alignment_sensitivity`).
ALIGNMENT_PARAMETERS = {"none": 0, "se3": 6, "origin": 6, "sim3": 7, "4dof": 4, "scale": 1}

#: A shared direction is tested when the data determine at least this share of its prior
#: variance (eigenvalue of the estimate's covariance, whitened units): below it the direction
#: is (nearly) unobservable, e.g. absorbed by the alignment, and left out of the chi-square.
MIN_OBSERVED_VARIANCE = 1e-2


def alignment_sensitivity(position: ArrayLike, method: str) -> np.ndarray | None:
    r"""``K_k = d e_k / d a`` (N, 6, m): how a small change ``a`` of an alignment ``method`` (a key of
    :data:`ALIGNMENT_PARAMETERS`) moves the pose errors at ground-truth positions (N, 3) m; None for
    "none" (docs/evaluation.md#errors-shared-by-the-deployment).
    """
    if method not in ALIGNMENT_PARAMETERS:
        raise ValueError(f"Expected an alignment in {tuple(ALIGNMENT_PARAMETERS)}, got {method!r}")
    if method == "none":
        return None
    p = np.asarray(position, dtype=float)
    N = p.shape[0]
    if method == "scale":
        K = np.zeros((N, 6, 1))
        K[:, :3, 0] = p
        return K
    c = p - p.mean(axis=0)
    rigid = np.zeros((N, 6, 6))
    rigid[:, :3, :3] = np.eye(3)
    rigid[:, :3, 3:] = -hat(c)
    rigid[:, 3:, 3:] = np.eye(3)
    if method == "4dof":
        return rigid[:, :, [0, 1, 2, 5]]
    if method == "sim3":
        scale = np.zeros((N, 6, 1))
        scale[:, :3, 0] = c
        return np.concatenate([rigid, scale], axis=2)
    return rigid


@dataclass(frozen=True)
class SharedTest:
    """The shared parameters' GLS estimate ``theta`` (k,) tested against its own covariance:
    ``statistic`` over the ``dof`` observed directions (above :data:`MIN_OBSERVED_VARIANCE`), its
    ``1 - alpha`` ``interval`` and ``p_value``; ``tau`` of the whitened residual; ``absorbed``
    alignment parameters; ``consistent`` (one-sided with ``upper``).
    """

    theta: np.ndarray
    statistic: float
    dof: int
    interval: tuple[float, float]
    p_value: float
    tau: float
    absorbed: int
    consistent: bool
    alpha: float
    upper: bool = False

    def to_dict(self) -> dict:
        return {"statistic": float(self.statistic), "dof": int(self.dof),
                "test": "one-sided (upper)" if self.upper else "two-sided",
                "interval": [float(v) for v in self.interval], "p_value": float(self.p_value),
                "consistent": bool(self.consistent), "alpha": float(self.alpha),
                "time_correlation": float(self.tau), "alignment_parameters": int(self.absorbed),
                "k": int(self.theta.size)}


@dataclass(frozen=True)
class SplitVerdict:
    """The split test's verdict for one NEES: ``shared`` (:class:`SharedTest`), ``varying``
    (:class:`NeesResult` of the residual, scaled to mean ``dof``), ``consistent`` (both, each at
    ``alpha / 2``), ``names`` of the shared parameters.
    """

    shared: SharedTest
    varying: NeesResult
    consistent: bool
    names: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        v = self.varying
        top = np.argsort(-np.abs(self.shared.theta))[:5]
        return {
            "consistent": bool(self.consistent),
            "shared": {**self.shared.to_dict(),
                       "largest": {(self.names[j] if j < len(self.names) else str(j)):
                                   float(self.shared.theta[j]) for j in top}},
            "varying": {"mean": float(v.mean), "dof": int(v.dof),
                        "fraction_inside_95": float(v.fraction_inside_95),
                        "consistent": bool(v.consistent), "n_eff": float(v.n_eff),
                        "mean_interval": [float(x) for x in v.mean_interval],
                        "fraction_interval": [float(x) for x in v.fraction_interval],
                        "alpha": float(v.alpha)},
        }


def _whiten(D: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``chol(D)^-1 X`` for (N, d, d) covariances and (N, d, ...) right-hand sides."""
    Lc = np.linalg.cholesky(D)
    if X.ndim == 2:
        return np.linalg.solve(Lc, X[..., None])[..., 0]
    return np.linalg.solve(Lc, X)


def shared_error_test(
    e: ArrayLike,
    D: ArrayLike,
    L: ArrayLike,
    K: ArrayLike | None = None,
    *,
    alpha: float = 0.05,
    names: tuple[str, ...] = (),
    upper: bool = False,
) -> tuple[SplitVerdict, SplitVerdict]:
    r"""The split test of errors ``e`` (N, d) (d = 6 poses, 3 positions; m, rad) against
    ``C = blockdiag(D_k) + L L^T`` with alignment sensitivity ``K`` (N, d, m) or None.

    ``D`` (N, d, d) varying covariances, ``L`` (N, d, k) shared factor, ``names`` its parameters;
    ``upper``: one-sided tests (an estimate without covariance). Returns the ``position`` and
    ``pose`` :class:`SplitVerdict` (pose None for d = 3);
    docs/evaluation.md#errors-shared-by-the-deployment.
    """
    e = np.asarray(e, dtype=float)
    D = np.asarray(D, dtype=float)
    L = np.asarray(L, dtype=float)
    N, d_err = e.shape
    if d_err not in (3, 6):
        raise ValueError(f"Expected errors of 6 (pose) or 3 (position) components, got {d_err}")
    k = L.shape[2]
    U = L if K is None else np.concatenate([L, np.asarray(K, dtype=float)], axis=2)
    m = U.shape[2] - k
    try:
        Ut = _whiten(D, U)
        et = _whiten(D, e)
        Ut3 = Ut if d_err == 3 else _whiten(D[:, :3, :3], U[:, :3])
        et3 = et if d_err == 3 else _whiten(D[:, :3, :3], e[:, :3])
    except np.linalg.LinAlgError:
        raise ValueError("Expected positive definite varying covariances") from None
    A = np.einsum("nip,niq->pq", Ut, Ut)
    A3 = np.einsum("nip,niq->pq", Ut3, Ut3)
    b = np.einsum("nip,ni->p", Ut, et)
    Lam = np.diag(np.r_[np.ones(k), np.zeros(m)])
    Hinv = np.linalg.pinv(Lam + A, hermitian=True)
    est = Hinv @ b
    theta = est[:k]
    rt = et - Ut @ est
    r3 = et3 - Ut3 @ est
    tau = float(np.mean([integrated_autocorrelation_time(rt[:, c]) for c in range(d_err)]))
    E = np.eye(k + m)[:, :k]
    GL = E - Hinv[:, :k]
    cov = tau * (Hinv - Hinv @ Lam @ Hinv) + GL @ GL.T
    w, Q = np.linalg.eigh(cov[:k, :k])
    keep = w > MIN_OBSERVED_VARIANCE
    z = Q[:, keep].T @ theta
    stat = float(np.sum(z * z / w[keep]))
    dof = int(np.count_nonzero(keep))
    a_s = alpha / 2
    if dof:
        interval = (float(stats.chi2.ppf(a_s / 2, dof)), float(stats.chi2.ppf(1 - a_s / 2, dof)))
        p_value = float(stats.chi2.sf(stat, dof))
        ok = stat <= interval[1] and (upper or interval[0] <= stat)
    else:
        interval, p_value, ok = (0.0, 0.0), 1.0, True
    shared = SharedTest(theta, stat, dof, interval, p_value, tau, m, bool(ok), alpha, upper)
    Hk = Hinv[:, :k]
    M = 2 * Hinv - Hinv @ A @ Hinv - Hk @ Hk.T
    out = []
    for d, r, Ad in ((3, r3, A3), (6, rt, A))[:d_err // 3]:
        expected = (d * N - float(np.trace(M @ Ad))) / (d * N)
        varying = nees_consistency(np.einsum("ni,ni->n", r, r) / expected, d, alpha=a_s)
        if upper:
            varying = replace(varying, consistent=bool(
                varying.mean <= varying.mean_interval[1]
                and varying.fraction_inside_95 >= varying.fraction_interval[0]))
        out.append(SplitVerdict(shared, varying, bool(ok and varying.consistent), tuple(names)))
    return out[0], (out[1] if d_err == 6 else None)


def with_split_verdict(
    nees: tuple[NeesResult, ...],
    e: ArrayLike,
    D: ArrayLike,
    L: ArrayLike,
    K: ArrayLike | None = None,
    *,
    names: tuple[str, ...] = (),
    upper: bool = False,
) -> tuple[NeesResult, ...]:
    """The position and pose NEES ``nees`` (the position one alone for position errors) with
    the split test's verdict
    (:func:`shared_error_test` of ``e``, ``D``, ``L``, ``K``): ``consistent`` becomes the
    split verdict and ``split`` holds it; ``mean`` and ``fraction_inside_95`` stay those of
    the NEES against the total covariance. Raises ``ValueError`` where
    :func:`shared_error_test` does."""
    verdicts = shared_error_test(e, D, L, K, names=names, upper=upper)
    return tuple(replace(n, consistent=v.consistent, split=v)
                 for n, v in zip(nees, verdicts, strict=False))
