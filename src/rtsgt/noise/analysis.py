"""The paper's per-source analysis: ``sqrt(||Sigma||_F)`` of each source, binned by range.

Vaidis et al. 2023 (Fig. 4, Table II): medians in mm per range bin (0-75, 75-150, > 150 m);
docs/noise-model.md#per-source-analysis.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.noise.propagation import propagate

#: The range bins of the paper, m.
PAPER_RANGE_EDGES = (0.0, 75.0, 150.0, np.inf)


def frobenius_norm_mm(cov: ArrayLike) -> np.ndarray:
    """``sqrt(||Sigma||_F)`` in mm of covariances ``cov`` (..., 3, 3) in m^2."""
    c = np.asarray(cov, dtype=float)
    if c.shape[-2:] != (3, 3):
        raise InputError(f"Expected covariances of shape (..., 3, 3), got {c.shape}")
    return np.sqrt(np.sqrt(np.einsum("...ij,...ij->...", c, c))) * 1e3


def source_norms_mm(track, *, total: bool = True) -> dict[str, np.ndarray]:
    """``sqrt(||Sigma_s||_F)`` (N,), mm, of every source of a track (its ``cov_by_source``)
    alone, plus the total's under ``"total"`` when ``total``."""
    out = {s: frobenius_norm_mm(c) for s, c in track.cov_by_source.items()}
    if total:
        out["total"] = frobenius_norm_mm(track.cov)
    return out


def authors_source_norms_mm(
    obs, model, *, base: str = "instrument", **propagate_kwargs
) -> dict[str, np.ndarray]:
    """The authors' variant, ``sqrt(||Sigma_(base + s) - Sigma_base||_F)`` (N,), mm, per source
    of ``model`` (``base`` alone: ``sqrt(||Sigma_base||_F)``), by :func:`rtsgt.noise.propagate`
    with ``propagate_kwargs``."""

    if base not in model.sources:
        raise InputError(f"The base source {base!r} is not in the model's sources {model.sources}")
    ref = propagate(obs, model.with_sources((base,)), **propagate_kwargs).cov
    out = {base: frobenius_norm_mm(ref)}
    for s in model.sources:
        if s == base:
            continue
        both = propagate(obs, model.with_sources((base, s)), **propagate_kwargs).cov
        out[s] = frobenius_norm_mm(both - ref)
    return out


@dataclass(frozen=True)
class RangeBins:
    """Medians of a per-measurement quantity in range bins: bin k is ``[edges[k], edges[k+1])``
    (K + 1 edges, m), its ``median`` (NaN if empty) and ``count`` (K,), and the median and
    count of all finite values."""

    edges: np.ndarray
    median: np.ndarray
    count: np.ndarray
    overall_median: float
    overall_count: int

    def labels(self) -> list[str]:
        """Human-readable bin labels ("0-75 m", ..., "> 150 m")."""
        out = []
        for lo, hi in zip(self.edges[:-1], self.edges[1:], strict=True):
            out.append(f"> {lo:g} m" if np.isinf(hi) else f"{lo:g}-{hi:g} m")
        return out

    def as_dict(self) -> dict:
        """JSON-friendly form."""
        return {
            "edges_m": [float(e) for e in self.edges],
            "median": [None if np.isnan(m) else float(m) for m in self.median],
            "count": [int(c) for c in self.count],
            "overall_median": None if np.isnan(self.overall_median) else self.overall_median,
            "overall_count": self.overall_count,
        }


def bin_by_range(
    values: ArrayLike | Mapping[str, ArrayLike],
    range_m: ArrayLike,
    edges: Sequence[float] = PAPER_RANGE_EDGES,
) -> RangeBins | dict[str, RangeBins]:
    """:class:`RangeBins` of ``values`` (N,) (a mapping of them gives a mapping) by the range
    ``range_m`` (N,), m, of each measurement; increasing ``edges``, m (default the paper's
    0/75/150/inf m)."""
    if isinstance(values, Mapping):
        return {k: bin_by_range(v, range_m, edges) for k, v in values.items()}
    v = np.asarray(values, dtype=float)
    r = np.asarray(range_m, dtype=float)
    e = np.asarray(edges, dtype=float)
    if v.ndim != 1 or r.shape != v.shape:
        raise InputError(f"Expected values and range_m of the same shape (N,), got {v.shape}, {r.shape}")
    if e.ndim != 1 or e.shape[0] < 2 or np.any(np.diff(e) <= 0):
        raise InputError(f"Expected at least two increasing bin edges, got {list(e)}")
    ok = np.isfinite(v) & np.isfinite(r)
    k = np.searchsorted(e, r, side="right") - 1
    inside = ok & (k >= 0) & (k < e.shape[0] - 1)
    nb = e.shape[0] - 1
    counts = np.bincount(k[inside], minlength=nb)
    med = np.full(nb, np.nan)
    for b in np.flatnonzero(counts):  # loop over a handful of bins, not over measurements
        med[b] = np.median(v[inside & (k == b)])
    overall = float(np.median(v[ok])) if np.any(ok) else float("nan")
    return RangeBins(e, med, counts, overall, int(np.count_nonzero(ok)))


def summarize_sources(
    track, edges: Sequence[float] = PAPER_RANGE_EDGES
) -> dict[str, RangeBins]:
    """The paper's per-source table for one track: ``sqrt(||Sigma_s||_F)`` medians by range.

    ``summarize_sources(track)["instrument"].median`` are the per-bin medians (mm) of the
    instrument source; ``"total"`` is included.
    """
    if track.range_m is None:
        raise InputError("The track has no range_m; propagate() fills it")
    return bin_by_range(source_norms_mm(track), track.range_m, edges)
