r"""Noise-source analysis of one run: the numbers behind the paper's figures, for any deployment.

Per noise source and for all together: its size at the prisms (``sqrt(||Sigma_s||_F)`` in mm,
binned by range; docs/paper-figures.md#per-source-medians) and how much of it reaches the pose
(docs/paper-figures.md#how-much-reaches-the-pose). No files, no printing: :func:`analyze` takes
a run record (:class:`rtsgt.record.RunRecord`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from os import PathLike
from types import MappingProxyType
from typing import Any

import numpy as np

from rtsgt.choices import DEFAULT_BINS_M  # lower edges of the default range bins, m
from rtsgt.errors import InputError
from rtsgt.filtering.gates import position_uncertainty
from rtsgt.io.run_dir import read_run
from rtsgt.noise.analysis import bin_by_range, frobenius_norm_mm
from rtsgt.noise.sources import NOISE_SOURCES
from rtsgt.options import stage_rng
from rtsgt.pose import POSE_ENGINES, estimate_poses
from rtsgt.record import RunRecord

__all__ = [
    "ALL",
    "GP",
    "REFERENCE",
    "DEFAULT_BINS_M",
    "PAPER_CITATION",
    "PAPER_MEDIANS_MM",
    "POSE_MEASURES",
    "Analysis",
    "analyze",
    "analyze_dir",
    "bin_edges",
    "bin_labels",
    "nearest_psd",
    "paper_median_mm",
    "parse_bins",
    "pose_sigmas",
]

#: Name of the entry that combines every source.
ALL = "all"
#: Name of the pose entry of the reference prisms' survey uncertainty alone.
REFERENCE = "reference"
#: Name of the pose entry of the GP posterior alone (the white sources after interpolation).
GP = "gp"
#: Scalar measures of a 3x3 covariance block for the pose uncertainty.
POSE_MEASURES = ("sqrt_trace", "max_std")

#: Where :data:`PAPER_MEDIANS_MM` come from.
PAPER_CITATION = (
    "Vaidis, Dubois, Daum, Pomerleau, Giguère, 'Uncertainty analysis for accurate ground truth "
    "trajectories with robotic total stations', IROS 2023: medians of sqrt(||Sigma||_F) per "
    "noise source (Trimble S7, Forêt Montmorency deployments), as listed in rtsgt's "
    "docs/paper-figures.md"
)

_INF = math.inf
#: The paper's published medians of ``sqrt(||Sigma_s||_F)``, mm (:data:`PAPER_CITATION`):
#: ``"overall"`` and, where the paper gives them, per range bin keyed by ``(lower, upper)`` m.
PAPER_MEDIANS_MM = MappingProxyType({
    "instrument": MappingProxyType({"overall": 2.1, "bins": {(150.0, _INF): 2.78}}),
    "tilt": MappingProxyType({"overall": 0.06, "bins": {}}),
    "atmosphere": MappingProxyType({"overall": 0.16, "bins": {}}),
    "time_sync": MappingProxyType({"overall": 0.4, "bins": {}}),
    "calibration": MappingProxyType({
        "overall": 1.32, "bins": {(0.0, 75.0): 0.91, (75.0, 150.0): 1.88, (150.0, _INF): 5.49},
    }),
})


def paper_median_mm(source: str, lower: float | None = None,
                    upper: float | None = None) -> float | None:
    """The paper's median for a source, overall (no bounds) or for the bin ``[lower, upper)``.

    Returns None where the paper gives no number (another source, or another bin).
    """
    entry = PAPER_MEDIANS_MM.get(source)
    if entry is None:
        return None
    if lower is None and upper is None:
        return entry["overall"]
    return entry["bins"].get((float(lower), float(upper)))


def parse_bins(text: str | Sequence[float]) -> tuple[float, ...]:
    """Lower edges of the range bins from ``"0,75,150"`` (or a sequence), m.

    The last bin is open (``> 150 m``). The edges must be finite, non-negative and strictly
    increasing.
    """
    if isinstance(text, str):
        try:
            vals = [float(x) for x in text.replace(" ", "").split(",") if x != ""]
        except ValueError as exc:
            raise InputError(f"Expected range bins as comma-separated metres like "
                             f"'0,75,150', got {text!r}") from exc
    else:
        vals = [float(x) for x in text]
    if not vals:
        raise InputError("Expected at least one range bin edge, got none")
    e = np.asarray(vals)
    if not np.all(np.isfinite(e)) or np.any(e < 0) or np.any(np.diff(e) <= 0):
        raise InputError(f"Expected finite, non-negative, increasing bin edges, got {vals}")
    return tuple(vals)


def bin_edges(lower_edges: Sequence[float]) -> np.ndarray:
    """All edges including the open upper end: ``(0, 75, 150) -> [0, 75, 150, inf]``."""
    return np.append(np.asarray(parse_bins(lower_edges), dtype=float), np.inf)


def bin_labels(lower_edges: Sequence[float]) -> tuple[str, ...]:
    """``("0-75 m", "75-150 m", "> 150 m")`` for ``(0, 75, 150)``."""
    e = bin_edges(lower_edges)
    return tuple(f"> {lo:g} m" if np.isinf(hi) else f"{lo:g}-{hi:g} m"
                 for lo, hi in zip(e[:-1], e[1:], strict=True))


def pose_sigmas(cov: np.ndarray, measure: str = "sqrt_trace") -> tuple[np.ndarray, np.ndarray]:
    """Translation (mm) and rotation (mrad) uncertainty (T,) of pose covariances (T, 6, 6):
    ``sqrt(trace)`` (``"sqrt_trace"``) or ``sqrt(largest eigenvalue)`` (``"max_std"``) of each 3x3
    block; NaN where not finite.
    """
    if measure not in POSE_MEASURES:
        raise InputError(f"Expected pose measure in {POSE_MEASURES}, got {measure!r}")
    c = np.asarray(cov, dtype=float)
    if c.ndim != 3 or c.shape[1:] != (6, 6):
        raise ValueError(f"Expected pose covariances of shape (T, 6, 6), got {c.shape}")
    return (position_uncertainty(c[:, :3, :3], measure) * 1e3,
            position_uncertainty(c[:, 3:, 3:], measure) * 1e3)


def _median(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


def _num(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


@dataclass(frozen=True)
class Analysis:
    """Per-source noise analysis of one run (docs/paper-figures.md#per-source-medians).

    Measurements (N, all prisms): ``sources`` (then "all"), range bins ``bin_lower_m``,
    ``bin_labels``, ``bin_counts``, ``bin_shares``, ``n_measurements``; per measurement ``prism``,
    ``t`` s, ``range_m``, ``bin_index`` (-1 below the first edge); ``norm_mm`` per entry and its
    ``median_mm``, ``bin_median_mm`` (NaN for an empty bin). Poses (K): ``pose_sources``
    ("gp", "reference", "all" added), ``pose_t`` s, ``pose_cov`` (K, 6, 6), ``translation_mm``,
    ``rotation_mrad`` (:func:`pose_sigmas`) and their medians; ``pose_measure``, ``engine``,
    ``samples``; ``name`` of the deployment.
    """

    name: str
    sources: tuple[str, ...]
    bin_lower_m: tuple[float, ...]
    bin_labels: tuple[str, ...]
    bin_counts: tuple[int, ...]
    bin_shares: tuple[float, ...]
    n_measurements: int
    prism: np.ndarray
    t: np.ndarray
    range_m: np.ndarray
    bin_index: np.ndarray
    norm_mm: dict[str, np.ndarray]
    median_mm: dict[str, float]
    bin_median_mm: dict[str, tuple[float, ...]]
    pose_sources: tuple[str, ...]
    pose_t: np.ndarray
    pose_cov: dict[str, np.ndarray]
    translation_mm: dict[str, np.ndarray]
    rotation_mrad: dict[str, np.ndarray]
    pose_median_translation_mm: dict[str, float]
    pose_median_rotation_mrad: dict[str, float]
    pose_measure: str
    engine: str
    samples: int | None

    @property
    def bin_edges_m(self) -> np.ndarray:
        """All bin edges including the open end, m."""
        return bin_edges(self.bin_lower_m)

    def table_rows(self) -> list[dict[str, Any]]:
        """Rows of the per-source table: ours next to the paper's medians, mm.

        Each row: ``source``, ``median_mm``, ``paper_median_mm``, and ``bins``: a list of
        ``{"label", "median_mm", "paper_median_mm", "count", "share"}`` per range bin.
        """
        e = self.bin_edges_m
        rows = []
        for s in self.sources:
            bins = []
            for k, label in enumerate(self.bin_labels):
                bins.append({
                    "label": label,
                    "median_mm": _num(self.bin_median_mm[s][k]),
                    "paper_median_mm": paper_median_mm(s, e[k], e[k + 1]),
                    "count": int(self.bin_counts[k]),
                    "share": float(self.bin_shares[k]),
                })
            rows.append({"source": s, "median_mm": _num(self.median_mm[s]),
                         "paper_median_mm": paper_median_mm(s), "bins": bins})
        return rows

    def pose_rows(self) -> list[dict[str, Any]]:
        """Rows of the pose table: median translation (mm) and rotation (mrad) per entry."""
        return [{"source": s,
                 "translation_mm": _num(self.pose_median_translation_mm[s]),
                 "rotation_mrad": _num(self.pose_median_rotation_mrad[s])}
                for s in self.pose_sources]

    def to_dict(self, include_arrays: bool = False) -> dict[str, Any]:
        """JSON-ready form (medians, counts, parameters; the arrays on request)."""
        out: dict[str, Any] = {
            "name": self.name,
            "definition": {
                "prism": "sqrt(||Sigma_s||_F) of each source's 3x3 world covariance, mm",
                "pose": f"{self.pose_measure} of the 3x3 blocks of the 6x6 pose covariance: "
                        "translation mm, rotation mrad",
                "paper": PAPER_CITATION,
            },
            "bins": {"lower_m": list(self.bin_lower_m), "labels": list(self.bin_labels),
                     "counts": list(self.bin_counts), "shares": list(self.bin_shares)},
            "n_measurements": self.n_measurements,
            "sources": self.table_rows(),
            "pose": {"engine": self.engine, "samples": self.samples,
                     "measure": self.pose_measure, "n_poses": int(self.pose_t.shape[0]),
                     "sources": self.pose_rows()},
        }
        if include_arrays:
            out["arrays"] = {
                "prism": self.prism.tolist(), "t": self.t.tolist(),
                "range_m": self.range_m.tolist(),
                "norm_mm": {s: v.tolist() for s, v in self.norm_mm.items()},
                "pose_t": self.pose_t.tolist(),
                "translation_mm": {s: v.tolist() for s, v in self.translation_mm.items()},
                "rotation_mrad": {s: v.tolist() for s, v in self.rotation_mrad.items()},
            }
        return out


def _measurement_part(data: RunRecord, lower: tuple[float, ...]):
    prisms, ts, ranges = [], [], []
    per_source: dict[str, list[np.ndarray]] = {}
    sources = data.sources
    if not data.measurements:
        raise InputError("The run has no measured prism tracks to analyse")
    for pid, tr in data.measurements.items():
        if tr.range_m is None:
            raise InputError(f"The measurements of prism {pid} have no range; cannot bin them")
        n = len(tr)
        prisms.append(np.full(n, pid, dtype=object))
        ts.append(tr.t)
        ranges.append(tr.range_m)
        for s in sources:
            c = tr.cov_by_source.get(s)
            per_source.setdefault(s, []).append(
                np.full(n, np.nan) if c is None else frobenius_norm_mm(c))
        total = np.sum(list(tr.cov_by_source.values()), axis=0) if tr.cov_by_source else tr.cov
        per_source.setdefault(ALL, []).append(frobenius_norm_mm(total))
    r = np.concatenate(ranges)
    norm = {s: np.concatenate(v) for s, v in per_source.items()}
    edges = bin_edges(lower)
    binned = bin_by_range(norm, r, edges)
    k = np.searchsorted(edges, r, side="right") - 1
    k = np.where(np.isfinite(r) & (k >= 0) & (k < edges.size - 1), k, -1)
    counts = np.bincount(k[k >= 0], minlength=edges.size - 1)
    n_all = r.shape[0]
    shares = counts / n_all if n_all else np.zeros(counts.shape)
    return (tuple(sources) + (ALL,), np.concatenate(prisms).astype(str), np.concatenate(ts), r,
            k, norm, binned, counts, shares)


def _pose_times(data: RunRecord) -> np.ndarray:
    """Indices into ``data.prisms_t`` of the kept poses."""
    gt_t = data.groundtruth.t
    pt = data.prisms_t
    if gt_t.size == 0:
        return np.empty(0, dtype=int)
    idx = np.clip(np.searchsorted(pt, gt_t), 0, max(pt.size - 1, 0))
    prev = np.clip(idx - 1, 0, None)
    better = np.abs(pt[prev] - gt_t) < np.abs(pt[idx] - gt_t)
    idx = np.where(better, prev, idx)
    if pt.size == 0 or np.any(np.abs(pt[idx] - gt_t) > 1e-6):
        raise InputError("Some ground-truth pose times are not among the prisms' query times")
    return idx


#: The pose engine of the per-source split (:func:`analyze`): the linear propagation of each
#: source's prism covariance through the run's fit; the ``"all"`` entry is the run's own
#: covariance whatever the engine.
DEFAULT_ANALYSIS_ENGINE = "linear"


def nearest_psd(cov: np.ndarray) -> np.ndarray:
    """Covariances (..., n, n) symmetrised, with round-off negative eigenvalues set to zero where
    they occur (others bit for bit unchanged; non-finite matrices as they are).
    """
    c = np.array(cov, dtype=float)
    if c.size == 0:
        return c
    flat = c.reshape((-1,) + c.shape[-2:])
    ok = np.all(np.isfinite(flat), axis=(-1, -2))
    sym = 0.5 * (flat[ok] + np.swapaxes(flat[ok], -1, -2))
    w, V = np.linalg.eigh(sym)
    bad = w[:, 0] < 0
    if bad.any():
        m = np.einsum("kij,kj,klj->kil", V[bad], np.clip(w[bad], 0.0, None), V[bad])
        sym[bad] = 0.5 * (m + np.swapaxes(m, -1, -2))
    flat[ok] = sym  # 0.5 (A + A^T) is A itself, bit for bit, when A is symmetric
    return flat.reshape(c.shape)


def _pose_part(data: RunRecord, engine: str, samples: int, seed: int, measure: str):
    idx = _pose_times(data)
    q = data.prisms_xyz[idx]
    n = q.shape[1]
    zero_r = np.zeros((3 * n, 3 * n))
    rng = stage_rng(seed, "analysis")
    # the run's fit: a weighted one keeps the weights of the total covariance for every source
    fit = {"registration": data.options.pose.registration,
           "weight_cov_q": nearest_psd(data.prisms_cov[idx]), "weight_cov_r": data.reference_cov}
    cov: dict[str, np.ndarray] = {}
    if idx.size:
        for s, c in data.prisms_cov_by_source.items():
            cov[s] = estimate_poses(q, nearest_psd(c[idx]), data.reference_xyz, zero_r,
                                    engine=engine, samples=samples, rng=rng, **fit).cov
        if data.prisms_cov_gp is not None:
            cov[GP] = estimate_poses(q, nearest_psd(data.prisms_cov_gp[idx]),
                                     data.reference_xyz, zero_r, engine=engine,
                                     samples=samples, rng=rng, **fit).cov
        if np.any(data.reference_cov != 0):
            cov[REFERENCE] = estimate_poses(q, np.zeros(q.shape + (3,)), data.reference_xyz,
                                            data.reference_cov, engine=engine,
                                            samples=samples, rng=rng, **fit).cov
    else:
        for s in data.prisms_cov_by_source:
            cov[s] = np.empty((0, 6, 6))
    order = [s for s in NOISE_SOURCES if s in cov] + sorted(
        s for s in cov if s not in NOISE_SOURCES and s not in (GP, REFERENCE))
    order += [s for s in (GP, REFERENCE) if s in cov]
    cov = {s: cov[s] for s in order}
    gt_cov = data.groundtruth.cov
    cov[ALL] = np.empty((0, 6, 6)) if gt_cov is None else np.asarray(gt_cov)
    trans, rot = {}, {}
    for s, c in cov.items():
        trans[s], rot[s] = pose_sigmas(c, measure) if c.shape[0] else (np.empty(0), np.empty(0))
    return tuple(cov), data.groundtruth.t, cov, trans, rot


def analyze(
    data: RunRecord,
    *,
    bins: Sequence[float] | str = DEFAULT_BINS_M,
    engine: str | None = None,
    samples: int | None = None,
    seed: int | None = None,
    pose_measure: str = "sqrt_trace",
) -> Analysis:
    """:class:`Analysis` of a run record (just computed or read back: the same numbers).

    ``bins``: lower range edges, m (``"0,75,150"``; the last open); ``engine`` of the per-source
    poses (default :data:`DEFAULT_ANALYSIS_ENGINE`, docs/paper-figures.md#the-real-excerpt);
    ``samples`` and ``seed`` of its Monte Carlo (default the run's); ``pose_measure`` as
    :func:`pose_sigmas`.
    """
    lower = parse_bins(bins)
    if pose_measure not in POSE_MEASURES:
        raise InputError(f"Expected pose measure in {POSE_MEASURES}, got {pose_measure!r}")
    eng = DEFAULT_ANALYSIS_ENGINE if engine is None else engine
    if eng not in POSE_ENGINES:
        raise InputError(f"Expected engine {', '.join(POSE_ENGINES)}, got {eng!r}")
    m = int(data.options.pose.samples if samples is None else samples)
    sd = int(data.options.seed if seed is None else seed)
    (sources, prism, t, r, k, norm, binned, counts, shares) = _measurement_part(data, lower)
    pose_sources, pose_t, pose_cov, trans, rot = _pose_part(data, eng, m, sd, pose_measure)
    return Analysis(
        name=data.name,
        sources=sources,
        bin_lower_m=lower,
        bin_labels=bin_labels(lower),
        bin_counts=tuple(int(c) for c in counts),
        bin_shares=tuple(float(s) for s in shares),
        n_measurements=int(r.shape[0]),
        prism=prism, t=t, range_m=r, bin_index=k,
        norm_mm={s: norm[s] for s in sources},
        median_mm={s: float(binned[s].overall_median) for s in sources},
        bin_median_mm={s: tuple(float(x) for x in binned[s].median) for s in sources},
        pose_sources=pose_sources,
        pose_t=pose_t,
        pose_cov=pose_cov,
        translation_mm=trans,
        rotation_mrad=rot,
        pose_median_translation_mm={s: _median(v) for s, v in trans.items()},
        pose_median_rotation_mrad={s: _median(v) for s, v in rot.items()},
        pose_measure=pose_measure,
        engine=eng,
        samples=m if eng == "mc" else None,
    )


def analyze_dir(run_dir: str | PathLike, *, bins: Sequence[float] | str = DEFAULT_BINS_M,
                **kwargs) -> Analysis:
    """Per-source analysis of a run directory written by ``rtsgt run``.

    Keyword arguments as :func:`analyze`.
    """
    return analyze(read_run(run_dir), bins=bins, **kwargs)
