"""Held-out windows of a prism track: the GP's prediction of each window of 1 s or 2 s of
measurements from all the others, without refitting, and the motion prior chosen by them.

Owns the windows (:data:`BLOCK_LENGTHS_S`, :func:`cv_blocks`), their joint prediction
(:func:`cv_windows`) and score (:func:`window_score`). The block cross-validation self-check
(:mod:`rtsgt.checks.block_cv`) judges a run by the same windows. Formulas and the choice of the
prior: docs/interpolation.md#choice-of-the-prior, docs/self-checks.md#block-cross-validation-of-the-tracks.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.interpolation.gp import GPTrack

__all__ = ["BLOCK_LENGTHS_S", "PAIR_LAGS", "cv_blocks", "cv_windows", "window_score"]

#: Lengths of the held-out blocks, s: alternating along each segment, one fold per length.
BLOCK_LENGTHS_S = (1.0, 2.0)
#: Neighbours (scored windows) whose correlation with a window enters the variance of the
#: NEES statistic of :mod:`rtsgt.checks.block_cv`: the next and the one after.
PAIR_LAGS = 2

_LOG_2PI = math.log(2.0 * math.pi)


def cv_blocks(t: ArrayLike, max_gap_s: float,
              lengths: tuple[float, ...] = BLOCK_LENGTHS_S) -> tuple[np.ndarray, np.ndarray]:
    """The blocks and folds of a track's measurements (module docstring).

    Parameters
    ----------
    t : array_like, shape (N,)
        Measurement times, s, increasing.
    max_gap_s : float
        A longer gap between consecutive measurements starts a new segment, whose blocks
        start again from its first measurement.
    lengths : tuple of float
        Block lengths, s, repeated in this order along each segment; block ``j`` of a period
        is fold ``j``.

    Returns
    -------
    block : ndarray of int, shape (N,)
        Block of each measurement, numbered from 0 in time order (empty blocks get none).
    fold : ndarray of int, shape (N,)
        Its fold (index into ``lengths``).
    """
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    new_seg = np.r_[True, np.diff(t) > max_gap_s]
    seg = np.cumsum(new_seg) - 1
    start = t[new_seg][seg]
    edges = np.cumsum(lengths)
    off = t - start
    period = np.floor(off / edges[-1])
    fold = np.minimum(np.searchsorted(edges, off - period * edges[-1], side="right"),
                      len(lengths) - 1)
    change = new_seg[1:] | (np.diff(period) != 0) | (np.diff(fold) != 0)
    return np.r_[0, np.cumsum(change)], fold


def _position_band(gp: GPTrack, width: int) -> np.ndarray:
    """``Cov(p_i, p_i+l)`` of the posterior positions for ``l = 0 .. width-1``, shape
    (N, width, 3, 3) (zero where ``i + l`` is past the end), by
    ``Cov(x_i, x_b) = Cov(x_i, x_b-1) S_b-1^-1 C_b-1`` (module docstring)."""
    S, C = gp.cov, gp.cross_cov
    n = S.shape[0]
    band = np.zeros((n, width, 3, 3))
    band[:, 0] = S[:, :3, :3]
    gain = np.linalg.solve(S[:-1], C)  # S_k^-1 C_k
    cur = S.copy()
    for lag in range(1, min(width, n)):
        cur = cur[:-1] @ gain[lag - 1:]
        band[: n - lag, lag] = cur[:, :3, :3]
    return band


def _joint(band: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``Cov(p_rows, p_cols)`` from the band: rows (G, a) and cols (G, b) knot indices;
    returns (G, 3a, 3b)."""
    r, c = rows[:, :, None], cols[:, None, :]
    lo, lag = np.minimum(r, c), np.abs(c - r)
    blocks = band[lo, lag]  # (G, a, b, 3, 3): Cov(p_lo, p_hi)
    blocks = np.where((r > c)[..., None, None], np.swapaxes(blocks, -1, -2), blocks)
    g, na, nb = blocks.shape[:3]
    return blocks.transpose(0, 1, 3, 2, 4).reshape(g, 3 * na, 3 * nb)


def cv_windows(track, gp: GPTrack, max_gap_s: float,
               lengths: tuple[float, ...] = BLOCK_LENGTHS_S,
               pairs: bool = True) -> dict[str, np.ndarray]:
    """Leave-one-window-out cross-validation of one track with the run's GP (module docstring).

    Parameters
    ----------
    track : tuple (t, xyz, cov)
        The measurements as given to the GP: times (N,) s, positions (N, 3) m, white
        covariances (N, 3, 3) m^2 (the GP's knots are these times).
    gp : GPTrack
        The run's GP of the track (its ``qc`` and ``qc_scale`` are those judged).
    max_gap_s : float
        Longest gap the run bridges, s: a window whose neighbours are farther apart is not
        scored.
    lengths : tuple of float
        Window lengths, s (:func:`cv_blocks`).
    pairs : bool
        Also compute ``pair_var`` (zeros without; the scores do not need it).

    Returns
    -------
    dict of ndarray, one entry per scored window, in time order
        ``first``, ``last`` (its measurements' indices), ``t_before``, ``t_after`` (the
        measurements around it, s), ``centre`` (midway between its first and last
        measurement, s), ``into_gap`` (from the centre to the nearest measurement kept, s),
        ``measurements``, ``nees`` (``3 m`` degrees of freedom), ``log_density`` (the log
        predictive density of the window's measurements, ``-0.5 (NEES_w + log|M_w| +
        3 m log 2 pi)``), and ``pair_var`` (W, LAGS): ``4 |C_w,w+l|_F^2``, what the pair of
        the window and the ``l``-th next scored window adds to the variance of the sum of
        their NEES.
    """
    t, y, R = (np.asarray(a, dtype=float) for a in track)
    n = t.size
    if gp.t.shape != t.shape or not np.array_equal(gp.t, t):
        raise InputError("Expected the GP's knots to be the track's measurement times")
    block, _ = cv_blocks(t, max_gap_s, lengths)
    first = np.flatnonzero(np.r_[True, np.diff(block) != 0]) if n else np.zeros(0, int)
    last = np.r_[first[1:] - 1, n - 1] if n else np.zeros(0, int)
    ok = (first > 0) & (last < n - 1)
    ok[ok] = t[last[ok] + 1] - t[first[ok] - 1] <= max_gap_s
    first, last = first[ok], last[ok]
    m = last - first + 1
    k = first.size
    out = {"first": first, "last": last, "t_before": t[first - 1], "t_after": t[last + 1],
           "centre": 0.5 * (t[first] + t[last]), "measurements": m, "nees": np.zeros(k),
           "log_density": np.zeros(k), "pair_var": np.zeros((k, PAIR_LAGS))}
    out["into_gap"] = np.minimum(out["centre"] - out["t_before"],
                                 out["t_after"] - out["centre"])
    if k == 0:
        return out
    width = int(max([m.max(), *(np.max(last[lag:] - first[:-lag]) + 1
                                for lag in range(1, PAIR_LAGS + 1) if k > lag)]))
    band = _position_band(gp, width)
    resid = y - gp.mean[:, :3]
    # per window: M = R_w - P_w, the covariance of its residuals in the fit with all the
    # measurements; NEES = r^T M^-1 r is the NEES of its prediction from all the others
    m_inv: dict[int, np.ndarray] = {}
    where = np.zeros(k, int)  # position of each window in its size group
    for mm in np.unique(m):
        sel = np.flatnonzero(m == mm)
        knots = first[sel, None] + np.arange(mm)
        M = -_joint(band, knots, knots).reshape(sel.size, mm, 3, mm, 3)
        di = np.arange(mm)
        M[:, di, :, di, :] += np.swapaxes(R[knots], 0, 1)
        M = M.reshape(sel.size, 3 * mm, 3 * mm)
        M = 0.5 * (M + np.swapaxes(M, 1, 2))
        inv = np.linalg.inv(M)
        r = resid[knots].reshape(sel.size, 3 * mm)
        out["nees"][sel] = np.einsum("wi,wij,wj->w", r, inv, r)
        # log|Sigma_w| = 2 log|R_w| - log|M_w| (module docstring)
        logdet_r = 2.0 * np.linalg.slogdet(R[knots])[1].sum(axis=1)
        logdet = logdet_r - np.linalg.slogdet(M)[1]
        out["log_density"][sel] = -0.5 * (out["nees"][sel] + logdet + 3 * mm * _LOG_2PI)
        m_inv[int(mm)] = inv
        where[sel] = np.arange(sel.size)
    # pairs of scored windows: Cov(r_a, r_b) = -P_ab, so Var(NEES_a + NEES_b) gains
    # 2 Cov(NEES_a, NEES_b) = 4 |M_a^-1/2 P_ab M_b^-1/2|_F^2 = 4 tr(M_a^-1 P_ab M_b^-1 P_ba)
    for lag in range(1, PAIR_LAGS + 1 if pairs else 1):
        a_idx = np.arange(k - lag)
        b_idx = a_idx + lag
        for ma in np.unique(m[a_idx]):
            for mb in np.unique(m[b_idx[m[a_idx] == ma]]):
                sel = a_idx[(m[a_idx] == ma) & (m[b_idx] == mb)]
                rows = first[sel, None] + np.arange(ma)
                cols = first[sel + lag, None] + np.arange(mb)
                P = _joint(band, rows, cols)
                left = m_inv[int(ma)][where[sel]] @ P
                right = m_inv[int(mb)][where[sel + lag]] @ np.swapaxes(P, 1, 2)
                out["pair_var"][sel, lag - 1] = 4.0 * np.einsum("wij,wji->w", left, right)
    return out


def window_score(track, gp: GPTrack, max_gap_s: float,
                 lengths: tuple[float, ...] = BLOCK_LENGTHS_S) -> dict[str, Any]:
    """Summed log predictive density of the held-out windows of one track (module docstring).

    Parameters
    ----------
    track : tuple (t, xyz, cov)
        The measurements as given to the GP: times (N,) s, positions (N, 3) m, white
        covariances (N, 3, 3) m^2.
    gp : GPTrack
        A GP of the track (either prior, with its ``qc`` and ``qc_scale``).
    max_gap_s : float
        Longest gap bridged, s (:func:`cv_windows`).
    lengths : tuple of float
        Window lengths, s.

    Returns
    -------
    dict
        JSON-ready: ``log_density`` (the sum over the scored windows; higher is better),
        ``nees_per_dof`` (``sum NEES_w / sum 3 m_w``; None without a window), ``windows`` and
        ``measurements`` scored.
    """
    w = cv_windows(track, gp, max_gap_s, lengths, pairs=False)
    dof = 3 * int(w["measurements"].sum())
    return {"log_density": float(w["log_density"].sum()),
            "nees_per_dof": float(w["nees"].sum() / dof) if dof else None,
            "windows": int(w["nees"].size), "measurements": dof // 3}
