"""Block cross-validation of the raw measurements, from the joint solution without a refit.

Each station's measurements are cut into blocks of 5 s and 10 s alternately
(:data:`RAW_BLOCK_LENGTHS_S`, the windows of :mod:`rtsgt.interpolation.windows`); a block
``b`` deleted, the other stations and the prior predict it, and its deletion residual has ``NEES_b = e_b^T Q_b^-1 e_b``, ``Q_b = R_b - H_b
Sigma H_b^T`` (``e_b`` the fitted residuals, ``Sigma`` the posterior: the knots' Markov chain
and the globals' factor of :class:`rtsgt.joint.sparse.ArrowSolution`). Derivation, effective
sample size and measurements: docs/joint.md#block-cross-validation-of-the-measurements.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from rtsgt.errors import RtsgtWarning
from rtsgt.interpolation.windows import cv_blocks
from rtsgt.joint.engine import (
    JointProblem,
    JointState,
    measurement_global_factor,
    measurement_terms,
)
from rtsgt.joint.noise import CHANNELS
from rtsgt.joint.relative import chain_gains, chain_products
from rtsgt.joint.sparse import ArrowSolution
from rtsgt.stats import failed, integrated_autocorrelation_time, ratio_interval, ratio_verdict

__all__ = ["MIN_BLOCKS", "RawBlocks", "raw_block_cv", "raw_block_summary"]

#: Fewest blocks for a verdict.
MIN_BLOCKS = 30
#: Lengths of the blocks, s, alternating along each station's measurements: longer than the
#: 1-12 s over which real total stations' noise is correlated (issue 23), so that a block's
#: neighbours do not predict its correlated error
#: (docs/joint.md#block-cross-validation-of-the-measurements).
RAW_BLOCK_LENGTHS_S = (5.0, 10.0)
#: Bytes of the blocks' deletion covariances assembled at once (bounds the temporaries: a
#: block of n measurements is (3n)^2 numbers, 0.3 MB at 20 Hz for 10 s).
_CHUNK_BYTES = 64e6


@dataclass(frozen=True)
class RawBlocks:
    """One row per held-out block: ``station`` (B,) index, ``t0``, ``t1`` (B,) s its first
    and last measurement, ``n`` (B,) measurements, ``nees`` (B,) of its deletion residual
    (3 n dof) and ``nees_channel`` (B, 3) of each channel's rows alone (Hz, V, d; n dof
    each, their marginal covariance)."""

    station: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    n: np.ndarray
    nees: np.ndarray
    nees_channel: np.ndarray


def _block_index(t, station, max_gap_s, lengths):
    """Measurement indices (B, n_max) of each block of one station, -1 padded, time order."""
    rows, owner = [], []
    for s in np.unique(station):  # a handful of stations
        idx = np.flatnonzero(station == s)
        idx = idx[np.argsort(t[idx], kind="stable")]
        block, _ = cv_blocks(t[idx], max_gap_s, lengths)
        order = np.argsort(block, kind="stable")
        bounds = np.flatnonzero(np.r_[True, np.diff(block[order]) != 0, True])
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            rows.append(idx[order[a:b]])
            owner.append(s)
    n_max = max((r.size for r in rows), default=0)
    out = np.full((len(rows), n_max), -1)
    for i, r in enumerate(rows):  # one row per block
        out[i, :r.size] = r
    return out, np.asarray(owner, dtype=int)


def raw_block_cv(prob: JointProblem, s: JointState, sol: ArrowSolution,
                 max_gap_s: float, lengths: tuple[float, ...] | None = None) -> RawBlocks:
    """Deletion NEES of every block of every station's measurements of the problem ``prob``
    at its solution ``s`` with the covariances ``sol`` (``want_cov``; of a mixture of prism
    hypotheses, its ``own``: the estimate's least squares, whose residuals these are; the
    mixture's spread would make ``Q_b`` indefinite); ``max_gap_s``: a longer gap starts new
    blocks."""
    sol = sol if sol.own is None else sol.own
    m = prob.meas
    r, *terms = measurement_terms(prob, s)
    Hk, k = terms[0], prob.of_meas
    u = measurement_global_factor(prob, sol, terms)  # (M, 3, G): the globals' part
    idx, owner = _block_index(m.t, m.station, max_gap_s,
                              RAW_BLOCK_LENGTHS_S if lengths is None else lengths)
    gains = chain_gains(sol)
    R = np.linalg.inv(m.info)
    nees = np.zeros(idx.shape[0])
    per = np.zeros((idx.shape[0], 3))
    step = max(1, int(_CHUNK_BYTES // (8 * (3 * max(idx.shape[1], 1)) ** 2)))
    for lo in range(0, idx.shape[0], step):
        nees[lo:lo + step], per[lo:lo + step] = _chunk_nees(idx[lo:lo + step], k, r, R, Hk,
                                                            u, sol, gains)
    valid = idx >= 0
    first, last = idx[:, 0], idx[np.arange(idx.shape[0]), valid.sum(axis=1) - 1]
    return RawBlocks(owner, m.t[first], m.t[last], valid.sum(axis=1), nees, per)


def _chunk_nees(idx, of_meas, r, R, Hk, u, sol, gains):
    """Deletion NEES of blocks ``idx`` (B, n): ``Q_b`` assembled from ``Cov(x_ka, x_kb) =
    P_a ... P_b-1 Cov(x_kb)``, ``P_a`` the chain between consecutive measurements."""
    B, n = idx.shape
    valid = idx >= 0
    m = np.where(valid, idx, 0)
    k = np.where(valid, of_meas[m], of_meas[m[:, :1]])  # padding: no chain
    k = np.maximum.accumulate(k, axis=1)
    P = [chain_products(gains, k[:, a], k[:, a + 1]) for a in range(n - 1)]
    Q = np.zeros((B, n, 3, n, 3))
    Hm = Hk[m]
    for b in range(n):  # places in the blocks (a block's measurements, not all of them)
        C = sol.cov_var[k[:, b]]
        for a in range(b, -1, -1):
            if a < b:
                C = P[a] @ C
            S = Hm[:, a] @ C @ np.swapaxes(Hm[:, b], 1, 2) + u[m[:, a]] @ np.swapaxes(
                u[m[:, b]], 1, 2)
            Q[:, a, :, b, :] = -S
            Q[:, b, :, a, :] = -np.swapaxes(S, 1, 2)
    pad = ~(valid[:, :, None] & valid[:, None, :])
    Q[np.broadcast_to(pad[:, :, None, :, None], Q.shape)] = 0.0
    pos = np.arange(n)
    Q[:, pos, :, pos, :] += np.where(valid.T[:, :, None, None], R[m.T], np.eye(3))
    e = np.where(valid[:, :, None], r[m], 0.0)
    per = np.stack([np.einsum("bi,bi->b", e[:, :, c],
                              np.linalg.solve(Q[:, :, c, :, c], e[:, :, c, None])[:, :, 0])
                    for c in range(3)], axis=1)
    e = e.reshape(B, 3 * n)
    Q = Q.reshape(B, 3 * n, 3 * n)
    return np.einsum("bi,bi->b", e, np.linalg.solve(Q, e[:, :, None])[:, :, 0]), per


def _verdict(blocks: RawBlocks, mask: np.ndarray, channel: int | None = None
             ) -> dict[str, Any]:
    """NEES / dof of the blocks ``mask`` selects (one ``channel``'s rows, or all), its
    effective sample size, 95 % interval and verdict."""
    if channel is None:
        nees, dof = blocks.nees[mask], 3.0 * blocks.n[mask]
    else:
        nees, dof = blocks.nees_channel[mask, channel], 1.0 * blocks.n[mask]
    out: dict[str, Any] = {"blocks": int(mask.sum()), "measurements": int(blocks.n[mask].sum()),
                           "nees_per_dof": float(nees.sum() / dof.sum()) if dof.sum() else None}
    if mask.sum() < MIN_BLOCKS:
        out.update(n_eff=None, interval_95=None, verdict="too few blocks")
        return out
    # the blocks' NEES series (per station, time order) gives the effective sample size
    tau = integrated_autocorrelation_time(nees / dof)
    n_eff = float(dof.sum()) / tau
    interval = ratio_interval(n_eff)
    out.update(n_eff=round(n_eff, 1), interval_95=list(interval),
               verdict=ratio_verdict(out["nees_per_dof"], interval))
    return out


def raw_block_summary(blocks: RawBlocks, station_ids: tuple[str, ...],
                      warn: bool = True) -> dict[str, Any]:
    """JSON-ready: ``overall``, per station (``stations``) and per channel (``channels``:
    ``hz``, ``v``, ``d``, each channel's rows alone) ``blocks``, ``measurements``,
    ``nees_per_dof`` (3 dof per measurement, 1 per channel), ``n_eff``, ``interval_95``,
    ``verdict``; one warning per verdict not consistent (``warn``)."""
    out = {
        "statistic": "NEES / dof of blocks of one station's raw measurements (Hz, V, d), each "
                     "predicted from the other stations and the prior; 1 if the measurements' "
                     "covariance and the motion prior are honest",
        "block_lengths_s": list(RAW_BLOCK_LENGTHS_S),
        "overall": _verdict(blocks, np.ones(blocks.nees.shape, bool)),
        "stations": {sid: _verdict(blocks, blocks.station == i)
                     for i, sid in enumerate(station_ids) if np.any(blocks.station == i)},
        "channels": {c: _verdict(blocks, np.ones(blocks.nees.shape, bool), j)
                     for j, c in enumerate(CHANNELS)},
    }
    if warn:
        named = ([("the whole run", out["overall"])]
                 + [(f"station {s}", v) for s, v in out["stations"].items()]
                 + [(f"channel {c}", v) for c, v in out["channels"].items()])
        for name, v in failed(named):
            lo, hi = v["interval_95"]
            warnings.warn(
                f"self-check, block cross-validation of the raw measurements over {name} "
                f"({v['blocks']} blocks): NEES / dof = {v['nees_per_dof']:.2f}, outside "
                f"[{lo:.2f}, {hi:.2f}] (95 %, {v['n_eff']:.0f} effective samples)",
                RtsgtWarning, stacklevel=2)
    return out
