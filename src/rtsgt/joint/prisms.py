"""The prisms' body positions as estimated parameters with the survey as their prior, and the
test of each prism against its survey (a prism moved after the survey is found, not trusted):
docs/joint.md#prism-positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import null_space
from scipy.stats import chi2

from rtsgt.geometry.so3 import hat

#: Prior standard deviation (m) given to a direction the survey's covariance fixes exactly
#: (the survey's own frame: points that define it). As the stations' ``FIXED_SIGMA``.
FIXED_SIGMA_M = 1e-7
#: A direction of a prism's move is determined by the data when their information on it is at
#: least this fraction of the survey's, taken on the survey's common scale (the move's sigma
#: at most 10 times the survey's least precise direction's, :func:`_common_scale`); the
#: others (the gauge: a rigid motion of the prisms is the pose's) are neither tested nor freed.
DETERMINED_RATIO = 0.01
#: False-alarm rate of the test that a prism moved, over all prisms of a deployment
#: (Bonferroni: each prism's at this over their number).
TEST_ALPHA = 1e-3


def prism_prior_info(cov: np.ndarray) -> np.ndarray | None:
    """Information (3P, 3P) of the survey's covariance ``cov`` (3P, 3P) m^2 (directions of
    zero variance held at :data:`FIXED_SIGMA_M`), or None for a survey known exactly (the
    prisms are then held)."""
    cov = np.asarray(cov, dtype=float)
    if not np.any(cov):
        return None
    return np.linalg.inv(cov + FIXED_SIGMA_M**2 * np.eye(cov.shape[0]))


@dataclass(frozen=True)
class PrismTests:
    """Each prism's test against its survey: ``displacement`` (P, 3) m the move of prism j
    alone that the data support (its survey freed, the others kept), ``cov`` (P, 3, 3) m^2
    its covariance (in the determined directions), ``stat`` (P,) the test statistic (chi^2
    with ``dof`` (P,) degrees of freedom if it did not move), ``directions`` (P, 3, 3) the
    eigenvectors (columns) of the data's information on the move outside the prism's gauge
    and ``determined`` (P, 3) which of them the data determine (:data:`DETERMINED_RATIO`;
    never the gauge), ``information`` (P, 3, 3) the data's information (``N_jj``, the gauge's
    included), ``prior`` (P, 3, 3) the survey's (``info_jj``, on the common scale:
    :func:`_common_scale`) and ``size`` (P,) m the size of the move over every direction the
    data determine, the gauge's included (where only the motion model sees it): the scale of
    a freed prism's survey where it is kept (:func:`free_prism`)."""

    displacement: np.ndarray
    cov: np.ndarray
    stat: np.ndarray
    dof: np.ndarray
    directions: np.ndarray
    determined: np.ndarray
    information: np.ndarray
    prior: np.ndarray
    size: np.ndarray

    def critical(self, alpha: float = TEST_ALPHA) -> np.ndarray:
        """Critical values (P,) of ``stat`` at the family-wise rate ``alpha`` (Bonferroni)."""
        return chi2.ppf(1.0 - alpha / self.stat.size, np.maximum(self.dof, 1))


def prism_tests(survey: np.ndarray, info: np.ndarray, xyz: np.ndarray,
                cov: np.ndarray, trusted: np.ndarray | None = None) -> PrismTests:
    """Outlier tests of the survey's prism groups (Baarda's test for a group of the prior).

    Estimates ``xyz`` (P, 3) with posterior ``cov`` (3P, 3P) under the prior ``N(survey,
    info^-1)``: the prior's residual ``v = xyz - survey`` has covariance ``Q = info^-1 - cov``
    under no move; ``u = info v``, ``N = info Q info = info - info cov info`` (the data's
    information on a move);
    prism j's move ``N_jj^+ u_j``, statistic ``u_j^T N_jj^+ u_j`` over the determined
    directions of ``N_jj`` outside prism j's gauge (:func:`gauge_directions` with the other
    ``trusted`` (P,) prisms, None: all): a move there is a rotation of the body frame, which
    no measurement sees and only the motion model places; it is neither tested nor freed
    (docs/joint.md#a-prisms-gauge-is-not-tested)."""
    P = survey.shape[0]
    v = (xyz - survey).ravel()
    N = info - info @ cov @ info
    u = (info @ v).reshape(P, 3)
    blk, pri = _prism_blocks(N), _prism_blocks(info)
    blk = 0.5 * (blk + np.swapaxes(blk, 1, 2))
    trusted = np.ones(P, bool) if trusted is None else np.asarray(trusted, bool)
    pri = _common_scale(pri, trusted)
    outside = np.stack([np.eye(3) - G @ G.T for G in
                        (gauge_directions(survey, trusted & (np.arange(P) != j), j)
                         for j in range(P))])  # a handful of prisms
    U, det, Ninv, disp = _moves(outside @ blk @ outside, pri, u)
    stat = np.clip(np.einsum("pi,pi->p", u, disp), 0.0, None)
    size = np.linalg.norm(_moves(blk, pri, u)[3], axis=1)
    return PrismTests(disp, Ninv, stat, det.sum(axis=1), U, det, blk, pri, size)


def _moves(N: np.ndarray, prior: np.ndarray, u: np.ndarray):
    """Eigenvectors (P, 3, 3) of the data's information ``N`` (P, 3, 3) on each prism's move,
    which the data determine (P, 3) against ``prior`` (P, 3, 3), the moves' covariance
    ``N^+`` (P, 3, 3) over those and the moves ``N^+ u`` (P, 3) from the scores ``u``."""
    w, U, det = _determined(N, prior)
    winv = np.where(det, 1.0 / np.where(det, w, 1.0), 0.0)
    Ninv = (U * winv[:, None, :]) @ np.swapaxes(U, 1, 2)
    return U, det, Ninv, np.einsum("pij,pj->pi", Ninv, u)


def _prism_blocks(M: np.ndarray) -> np.ndarray:
    """The prisms' 3x3 diagonal blocks (P, 3, 3) of a (3P, 3P) matrix ``M``."""
    P = M.shape[0] // 3
    return np.stack([M[3 * j:3 * j + 3, 3 * j:3 * j + 3] for j in range(P)])


def _common_scale(prior: np.ndarray, trusted: np.ndarray) -> np.ndarray:
    """The prisms' survey information blocks (P, 3, 3), each capped at the survey's least
    precise direction (the smallest eigenvalue of the ``trusted`` (P,) prisms' blocks: a
    freed prism's survey is gone where the data determine it): a prism surveyed more tightly
    than the others (or defining the survey's frame) is judged on the same scale, else the
    data could never determine its move (docs/joint.md#which-prism-moved)."""
    lam, V = np.linalg.eigh(prior)
    cap = lam[trusted].min() if np.any(trusted) else lam.max()
    return (V * np.minimum(lam, cap)[:, None, :]) @ np.swapaxes(V, 1, 2)


def _determined(N: np.ndarray, prior: np.ndarray):
    """Eigenvalues (..., n), eigenvectors (..., n, n) of the data's information ``N``
    (..., n, n) and which directions it determines against the ``prior``'s information."""
    w, U = np.linalg.eigh(N)
    prior_w = np.einsum("...ia,...ij,...ja->...a", U, prior, U)
    return w, U, (w > 0.0) & (w >= DETERMINED_RATIO * prior_w)


def _fixing(p_body: np.ndarray, trusted: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motions (6, m) (small ``(shift, rotation)`` about the body frame's origin)
    that keep the ``trusted`` prisms (boolean (P,)) of ``p_body`` (P, 3) fixed, and how far
    each moves prism ``j`` (3, m)."""
    if not np.any(trusted):
        null = np.eye(6)
    else:
        rows = np.concatenate([np.concatenate([np.eye(3), -hat(p)], axis=1)
                               for p in p_body[trusted]])
        _, sv, Vt = np.linalg.svd(rows)
        null = Vt[np.sum(sv > 1e-9 * sv[0]):].T
    return null, np.concatenate([np.eye(3), -hat(p_body[j])], axis=1) @ null


def gauge_directions(p_body: np.ndarray, trusted: np.ndarray, j: int) -> np.ndarray:
    """Orthonormal directions (3, m) in which prism ``j`` moves under the rigid motions that
    keep the ``trusted`` prisms (boolean (P,)) of ``p_body`` (P, 3) fixed: none for three or
    more not collinear, the tangent of the circle about their line for two (the body frame
    is the survey's: there prism j's survey defines it)."""
    _, D = _fixing(p_body, trusted, j)
    if D.size == 0:
        return np.zeros((3, 0))
    U, sd, _ = np.linalg.svd(D, full_matrices=False)
    return U[:, sd > 1e-9 * max(sd.max(), 1e-300)]


def blind_moves(p_body: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """What no station sees of a prism's move, per prism ``j`` of ``p_body`` (P, 3) m (the
    others where the survey puts them): the directions (3, m) of a move of ``j`` that a
    rigid motion keeping the others makes (:func:`gauge_directions`: for three prisms the
    normal of their plane, for four or more off one plane none; each direction's largest
    component positive) and the body frame's turn (m,) rad per m of move along each, the
    least rotation of a rigid motion that makes it (for three prisms ``1 / h``, ``h`` the
    prism's distance from the others' line; for two ``1 / L`` over their distance). Every
    pose is turned so by a move the survey does not know of
    (docs/joint.md#what-no-station-sees)."""
    out = []
    for j in range(p_body.shape[0]):  # a handful of prisms
        trusted = np.arange(p_body.shape[0]) != j
        null, D = _fixing(p_body, trusted, j)
        g = gauge_directions(p_body, trusted, j)
        if g.size:  # each direction's largest component positive
            g = g * np.sign(g[np.argmax(np.abs(g), axis=0), np.arange(g.shape[1])])
        c = np.linalg.pinv(D) @ g  # (n, m) one rigid motion along each, then the least turn
        Z = null_space(D)  # (motions keeping prism j too: about the line of two prisms)
        if Z.size:
            Rz = null[3:] @ Z
            c = c - Z @ np.linalg.lstsq(Rz, null[3:] @ c, rcond=None)[0]
        out.append((g, np.linalg.norm(null[3:] @ c, axis=0)))
    return out


def stability_factor(p_body: np.ndarray, sigma: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Moves since the survey of the prisms at ``p_body`` (P, 3) m that no station sees,
    ``sigma`` m (1 sigma per axis) along each prism's blind directions (:func:`blind_moves`),
    independent between prisms, as a consider parameter (docs/joint.md#what-no-station-sees):
    per unit of each whitened move (r of them, the prisms' blind directions in order), the
    prisms' body positions' change ``dp`` (3P, r) m and the body frame's right perturbation
    ``dxi`` (6, r) ``(rho, phi)`` at ``p_body``'s origin that keeps every prism where the
    stations see it (``rho + phi x p_j + dp_j = 0``, least squares: exact where the moves
    are a rigid motion's, as for three prisms), and each move's prism ``owner`` (r,)."""
    P = p_body.shape[0]
    blocks = [g for g, _ in blind_moves(p_body)]
    owner = np.repeat(np.arange(P), [g.shape[1] for g in blocks])
    dp = np.zeros((3 * P, owner.size))
    c = 0
    for j, g in enumerate(blocks):  # a handful of prisms
        dp[3 * j:3 * j + 3, c:c + g.shape[1]] = sigma * g
        c += g.shape[1]
    M = np.concatenate([np.concatenate([np.eye(3), -hat(p)], axis=1) for p in p_body])
    return -np.linalg.pinv(M) @ dp, dp, owner


def free_prism(info: np.ndarray, cov: np.ndarray, j: int, tests: PrismTests,
               gauge: np.ndarray) -> np.ndarray:
    """The prior information with prism ``j``'s survey (covariance ``cov`` (3P, 3P)) dropped
    in the directions the data determine (with its correlations with the other prisms) and
    kept in the ``gauge`` (3, m) directions and, orthogonal to them, those the data do not
    determine, where the move may be as large as the one the data show: there the survey's
    marginal variance plus ``|move|^2`` (``tests.displacement[j]``; docs/joint.md#prism-positions)."""
    out = info.copy()
    sl = slice(3 * j, 3 * j + 3)
    comp = np.linalg.svd(gauge, full_matrices=True)[0][:, gauge.shape[1]:]  # (3, 3-m)
    _, V, det = _determined(comp.T @ tests.information[j] @ comp,
                            comp.T @ tests.prior[j] @ comp)
    K = np.concatenate([gauge, comp @ V[:, ~det]], axis=1)
    out[sl, :] = 0.0
    out[:, sl] = 0.0
    if K.shape[1]:
        c = cov[sl, sl] + FIXED_SIGMA_M**2 * np.eye(3)  # as the prior's information
        move2 = float(tests.size[j]) ** 2
        blk = K @ np.linalg.inv(K.T @ c @ K + move2 * np.eye(K.shape[1])) @ K.T
        out[sl, sl] = 0.5 * (blk + blk.T)
    return out


@dataclass(frozen=True)
class PrismFit:
    """The prisms' estimated body positions: ``names`` (P,), ``xyz`` (P, 3) m, ``cov``
    (3P, 3P) m^2 (posterior), ``survey`` (P, 3) m (the prior's mean); ``moved`` (P,) the
    prisms found moved (their survey freed where the data determine it); ``shift`` (P, 3) m
    the estimate minus the survey; ``shift_sigma`` (P,) the test statistic's square root
    (for a moved prism: at its detection; chi with ``dof`` (P,) degrees of freedom if the
    prism did not move); ``weight`` (P,) the weight of the hypothesis that the prism moved
    (1 for one found alone, equal for the found and the others carried in the covariance,
    whose move explains the data as well or the trial preferred:
    docs/joint.md#which-prism-moved; 0 otherwise) and
    ``cost_above`` (P,) the score of another prism's hypothesis above the found one's, for
    every hypothesis solved beside it, carried or not (NaN for the others)."""

    names: tuple[str, ...]
    xyz: np.ndarray
    cov: np.ndarray
    survey: np.ndarray
    moved: np.ndarray
    shift_sigma: np.ndarray
    dof: np.ndarray
    weight: np.ndarray
    cost_above: np.ndarray

    @property
    def sigma(self) -> np.ndarray:
        """Posterior standard deviations (P, 3), m."""
        return np.sqrt(np.diag(self.cov)).reshape(-1, 3)

    @property
    def shift(self) -> np.ndarray:
        """Estimate minus survey (P, 3), m."""
        return self.xyz - self.survey

    @property
    def blind(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per prism the directions (3, m) of a move from the survey no station sees and
        the poses' turn (m,) rad per m of move along each (:func:`blind_moves` of
        ``survey``)."""
        return blind_moves(self.survey)

    @property
    def largest_sigma(self) -> np.ndarray:
        """Each prism's posterior standard deviation along its least determined direction
        (P,), m: for a prism found moved, where only the survey, the motion axes' prior and
        the motion prior place it (docs/joint.md#a-freed-prisms-gauge)."""
        lam = np.linalg.eigvalsh(_prism_blocks(self.cov))[:, -1]
        return np.sqrt(np.clip(lam, 0.0, None))


__all__ = ["DETERMINED_RATIO", "FIXED_SIGMA_M", "PrismFit", "PrismTests", "TEST_ALPHA",
           "blind_moves", "free_prism", "gauge_directions", "prism_prior_info", "prism_tests",
           "stability_factor"]
