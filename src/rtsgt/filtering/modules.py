"""Filtering modules 1 and 2 of Vaidis et al. (2022), "Accurate outdoor ground truth based on
total stations" (CRV), with the paper's parameters.

Module 1 (per station, raw polar observations): invalid, too far and duplicate measurements
out, blocks split at gaps over ``tau_s``, each block started at its anchor, then rate gates
(``tau_r``, ``tau_a``, ``tau_e``) against the last accepted measurement, evaluated without a
Python loop over measurements. Module 2 (across prisms): the intervals where every prism is
tracked, at least ``tau_l`` long, each series keeping one measurement either side. Both
reports keep a mask and a reason per measurement (:class:`FilterReport`), from which
:func:`removed_measurements` lists what was removed. docs/filtering.md.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.types import Observations, PrismTrack

__all__ = [
    "FilterParams", "FilterReport", "MODULE1_REASONS", "MODULE2_REASONS", "MODULE4_REASONS",
    "ANCHOR_NEIGHBOURS", "DEFAULT_MAX_DISTANCE_M", "RemovedMeasurements",
    "module1", "module2", "removed_measurements", "warn_tight_rate_gates",
]

#: Reasons of module 1, in the order they are tested.
MODULE1_REASONS = ("status", "non_finite", "max_distance", "duplicate_time", "rate_distance",
                   "rate_hz", "rate_v")

#: Largest raw slope distance module 1 keeps, m: the reference code's (norlab-ulaval
#: RTS_project, ``theodolite_utils.py``, ``distance <= 1000``).
DEFAULT_MAX_DISTANCE_M = 1000.0

#: How many following measurements of its block a block's first measurement is compared with
#: before it becomes the block's anchor (docs/filtering.md#module-1).
ANCHOR_NEIGHBOURS = 3

#: Reasons of module 2.
MODULE2_REASONS = ("not_all_tracked", "short_interval")

#: Reason of the measurements module 4 leaves out of the GP fits: inside a window of poses
#: the distance gate rejected (:mod:`rtsgt.filtering.gates`).
MODULE4_REASONS = ("distance_window",)

_TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class FilterParams:
    """Thresholds of the filtering modules (defaults: Vaidis et al. 2022): ``tau_r`` (m/s),
    ``tau_a`` and ``tau_e`` (rad/s), the largest rates of change of the slope distance, the
    horizontal direction and the zenith angle; ``tau_s`` (s), a longer gap splits a series;
    ``tau_l`` (s), the shortest interval module 2 keeps; ``max_distance`` (m), module 1's
    largest raw slope distance."""

    tau_r: float = 2.0
    tau_a: float = float(np.deg2rad(1.0))
    tau_e: float = float(np.deg2rad(1.0))
    tau_s: float = 3.0
    tau_l: float = 2.0
    max_distance: float = DEFAULT_MAX_DISTANCE_M

    def __post_init__(self) -> None:
        for name in ("tau_r", "tau_a", "tau_e", "tau_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"Expected {name} > 0, got {v!r}")
        if not (np.isfinite(self.max_distance) and self.max_distance > 0):
            raise InputError(f"Expected a finite max_distance > 0 m, got {self.max_distance!r}")
        if not (np.isfinite(self.tau_l) and self.tau_l >= 0):
            raise InputError(f"Expected tau_l >= 0, got {self.tau_l!r}")

    @classmethod
    def from_degrees(cls, tau_a_deg: float | None = None, tau_e_deg: float | None = None,
                     **others: float) -> FilterParams:
        """Parameters with the angular rates given in deg/s (``others``: ``tau_r``, ``tau_s``,
        ``tau_l``, ``max_distance``; the defaults where absent)."""
        for name, deg in (("tau_a", tau_a_deg), ("tau_e", tau_e_deg)):
            if deg is not None:
                others[name] = float(np.deg2rad(deg))
        return cls(**others)


@dataclass(frozen=True)
class FilterReport:
    """What a filtering module removed, and why: ``module`` (``"module1"``, ``"module2"``),
    ``n_in`` and ``n_kept`` measurements, ``removed`` counts per reason (every reason present),
    ``per_series`` the same per series given, ``n_blocks`` (module 1: blocks; module 2:
    intervals kept), and per series (N_i,) ``kept_masks`` and ``reasons`` (``""`` where kept)."""

    module: str
    n_in: int
    n_kept: int
    removed: Mapping[str, int]
    per_series: tuple[Mapping[str, int], ...] = field(default=())
    n_blocks: int = 0
    kept_masks: tuple[np.ndarray, ...] = field(default=(), repr=False, compare=False)
    reasons: tuple[np.ndarray, ...] = field(default=(), repr=False, compare=False)

    @property
    def n_removed(self) -> int:
        """Total number of measurements removed."""
        return self.n_in - self.n_kept

    def summary(self) -> str:
        """One line: ``module1: kept 200/215 (rate_hz 10, status 5)``."""
        parts = ", ".join(f"{k} {v}" for k, v in self.removed.items() if v)
        return f"{self.module}: kept {self.n_kept}/{self.n_in}" + (f" ({parts})" if parts else "")

    def as_dict(self) -> dict[str, Any]:
        """The counts as plain data (``summary.json`` ``filters``); the masks are left out."""
        return {"module": self.module, "n_in": self.n_in, "n_kept": self.n_kept,
                "removed": dict(self.removed), "per_series": [dict(c) for c in self.per_series],
                "n_blocks": self.n_blocks}


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angle difference wrapped into [-pi, pi] (exact, without rounding, when already there)."""
    return a - _TWO_PI * np.round(a / _TWO_PI)


def _gate(t, d, hz, v, i, js, p: FilterParams) -> np.ndarray:
    """Reason code of comparing measurements ``js`` with measurement ``i``: 0 = passes,
    1 = distance, 2 = horizontal direction, 3 = zenith angle (first failing gate)."""
    dt = t[js] - t[i]
    code = np.zeros(np.shape(js), dtype=int)
    bad_v = np.abs(v[js] - v[i]) > p.tau_e * dt
    bad_h = np.abs(_wrap(hz[js] - hz[i])) > p.tau_a * dt
    bad_d = np.abs(d[js] - d[i]) > p.tau_r * dt
    code[bad_v] = 3
    code[bad_h] = 2
    code[bad_d] = 1
    return code


def _anchors(t, d, hz, v, starts: np.ndarray, block_end: np.ndarray,
             p: FilterParams) -> tuple[np.ndarray, np.ndarray]:
    """The anchor of each block (module 1 step 3) and, per measurement, the reason code of its
    gate against the next measurement (the reason of a measurement rejected before an anchor).

    Returns ``anchor`` (K,) indices, one per block, and ``first_code`` (N,).
    """
    n = t.shape[0]
    k_all = np.arange(n)
    neighbours = np.minimum(ANCHOR_NEIGHBOURS, block_end - k_all - 1)
    disagrees = neighbours >= 2  # judged only with two neighbours or more
    first_code = np.zeros(n, dtype=int)
    for k in range(1, ANCHOR_NEIGHBOURS + 1):
        has = np.flatnonzero(disagrees & (neighbours >= k))
        if has.size == 0:
            break
        c = _gate(t, d, hz, v, has, has + k, p)
        if k == 1:
            first_code[has] = c
        disagrees[has] &= c > 0
    # the last two measurements of a block are never judged, so every block has an anchor
    ok = np.flatnonzero(~disagrees)
    return ok[np.searchsorted(ok, starts)], first_code


def _rate_filter(t, d, hz, v, p: FilterParams) -> tuple[np.ndarray, int]:
    """Anchors and the sequential rate gate, exactly, with vectorised episodes.

    Returns ``code`` (0 kept, 1-3 reason) per measurement, and the number of blocks.
    """
    n = t.shape[0]
    code = np.zeros(n, dtype=int)
    if n == 0:
        return code, 0
    new_block = np.empty(n, dtype=bool)
    new_block[0] = True
    new_block[1:] = np.diff(t) > p.tau_s
    starts = np.flatnonzero(new_block)
    sizes = np.diff(np.append(starts, n))
    block_end = np.repeat(np.append(starts[1:], n), sizes)  # exclusive end of each block
    anchor, first_code = _anchors(t, d, hz, v, starts, block_end, p)
    chain_start = np.repeat(anchor, sizes)
    before = np.flatnonzero(np.arange(n) < chain_start)  # rejected before their anchor
    code[before] = first_code[before]
    # raw consecutive pairs (j-1, j) after the anchor of the block
    raw = np.zeros(n, dtype=int)
    inner = np.flatnonzero(np.arange(n) > chain_start)
    if inner.size:
        raw[inner] = _gate(t, d, hz, v, inner - 1, inner, p)
    candidates = np.flatnonzero(raw)
    resume = 0  # the next raw pair to consider is (resume - 1, resume)
    for j in candidates:  # one iteration per episode of rejections, not per measurement
        if j < resume:
            continue
        i = j - 1  # last accepted: every pair between resume and j passed
        end = block_end[j]
        m = j
        width = 64
        found = -1
        while m < end:
            js = np.arange(m, min(m + width, end))
            c = _gate(t, d, hz, v, i, js, p)
            ok = np.flatnonzero(c == 0)
            stop = js.size if ok.size == 0 else ok[0]
            code[js[:stop]] = c[:stop]
            if ok.size:
                found = js[ok[0]]
                break
            m = js[-1] + 1
            width *= 4
        resume = end if found < 0 else found + 1
    return code, starts.size


def module1(
    obs: Observations, params: FilterParams | None = None
) -> tuple[Observations, FilterReport]:
    """Module 1 of Vaidis et al. (2022) on one station's polar observations ``obs`` (time order):
    ``(kept, report)``, the report's ``kept_masks[0]`` and ``reasons[0]`` indexed like ``obs``.
    Times going backwards raise :class:`~rtsgt.errors.InputError`."""
    p = FilterParams() if params is None else params
    if not isinstance(obs, Observations):
        raise InputError(f"Expected Observations, got {type(obs).__name__}")
    n = len(obs)
    reason = np.zeros(n, dtype=int)  # 0 kept, else 1 + index in MODULE1_REASONS
    reason[obs.status != 0] = 1
    finite = np.isfinite(obs.t) & np.isfinite(obs.hz) & np.isfinite(obs.v) & np.isfinite(obs.d)
    reason[(reason == 0) & ~finite] = 2
    reason[(reason == 0) & (obs.d > p.max_distance)] = 3
    idx = np.flatnonzero(reason == 0)
    t = obs.t[idx]
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size:
        k = back[0]
        raise InputError(
            f"Expected observations in time order, got t = {float(t[k + 1])!r} s "
            f"after t = {float(t[k])!r} s "
            f"(measurements {idx[k]} and {idx[k + 1]})",
            obs.source,
        )
    dup = np.flatnonzero(dt == 0) + 1
    reason[idx[dup]] = 4
    idx = np.flatnonzero(reason == 0)
    code, n_blocks = _rate_filter(obs.t[idx], obs.distance[idx], obs.hz[idx], obs.v[idx], p)
    reason[idx[code > 0]] = 4 + code[code > 0]
    counts = {r: int(np.sum(reason == i + 1)) for i, r in enumerate(MODULE1_REASONS)}
    keep = reason == 0
    names = np.array(("",) + MODULE1_REASONS)
    report = FilterReport("module1", n, int(keep.sum()), counts, (dict(counts),), n_blocks,
                          (_frozen(keep),), (_frozen(names[reason]),))
    return obs.select(keep), report


def _segments(t: np.ndarray, tau_s: float) -> np.ndarray:
    """(K, 2) index ranges [first, last] of the segments of ``t`` split at gaps > tau_s."""
    brk = np.flatnonzero(np.diff(t) > tau_s)
    first = np.concatenate([[0], brk + 1])
    last = np.concatenate([brk, [t.shape[0] - 1]])
    return np.stack([first, last], axis=1)


def _intersect(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersections of two sorted lists of disjoint closed intervals (K, 2), keeping a < b."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros((0, 2))
    lo = np.searchsorted(b[:, 1], a[:, 0], side="left")  # first b ending at/after a's start
    hi = np.searchsorted(b[:, 0], a[:, 1], side="right")  # b's starting at/before a's end
    cnt = np.maximum(hi - lo, 0)
    ia = np.repeat(np.arange(a.shape[0]), cnt)
    offset = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    ib = np.repeat(lo, cnt) + offset
    start = np.maximum(a[ia, 0], b[ib, 0])
    end = np.minimum(a[ia, 1], b[ib, 1])
    ok = start < end
    return np.stack([start[ok], end[ok]], axis=1)


def module2(
    tracks: Sequence[Observations | PrismTrack], params: FilterParams | None = None
) -> tuple[list, np.ndarray, FilterReport]:
    """Module 2 of Vaidis et al. (2022): keep the intervals where every prism of ``tracks`` (one
    series per prism, strictly increasing times on a common clock) is tracked, each series with
    its bracketing measurements. Returns ``(kept, intervals, report)``: the series restricted
    (same types and order), the kept intervals (K, 2), s, and the counts, masks and reasons per
    series. No series or bad times raise :class:`~rtsgt.errors.InputError`."""
    p = FilterParams() if params is None else params
    series = list(tracks)
    if not series:
        raise InputError("Expected at least one time series, got none")
    times = []
    for s_i, s in enumerate(series):
        t = np.asarray(getattr(s, "t", None), dtype=float)
        if t.ndim != 1:
            raise InputError(f"Expected series {s_i} to have times of shape (N,), got {t.shape}")
        if not np.all(np.isfinite(t)):
            raise InputError(f"Expected finite times in series {s_i}")
        if np.any(np.diff(t) <= 0):
            raise InputError(f"Expected strictly increasing times in series {s_i}")
        times.append(t)
    seg_idx = [_segments(t, p.tau_s) if t.size else np.zeros((0, 2), int) for t in times]
    seg_t = [t[s] if t.size else np.zeros((0, 2)) for t, s in zip(times, seg_idx, strict=True)]
    common = seg_t[0]
    common = common[common[:, 1] > common[:, 0]]
    for st in seg_t[1:]:
        common = _intersect(common, st)
    duration = common[:, 1] - common[:, 0]
    long_enough = duration >= p.tau_l
    kept_iv = common[long_enough]
    short_iv = common[~long_enough]
    kept, per_series, masks, reasons = [], [], [], []
    total = dict.fromkeys(MODULE2_REASONS, 0)
    n_in = n_kept = 0
    for s, t in zip(series, times, strict=True):
        n = t.size
        mark = np.zeros(n + 1, dtype=int)
        if kept_iv.shape[0] and n:
            lo = np.searchsorted(t, kept_iv[:, 0], side="right") - 1
            hi = np.searchsorted(t, kept_iv[:, 1], side="left")
            np.add.at(mark, np.clip(lo, 0, n - 1), 1)
            np.add.at(mark, np.clip(hi, 0, n - 1) + 1, -1)
        keep = np.cumsum(mark)[:n] > 0
        in_short = np.zeros(n, dtype=bool)
        if short_iv.shape[0] and n:
            k = np.searchsorted(short_iv[:, 0], t, side="right") - 1
            ok = k >= 0
            in_short[ok] = t[ok] <= short_iv[k[ok], 1]
        counts = {
            "not_all_tracked": int(np.sum(~keep & ~in_short)),
            "short_interval": int(np.sum(~keep & in_short)),
        }
        for r in MODULE2_REASONS:
            total[r] += counts[r]
        per_series.append(counts)
        why = np.where(in_short, "short_interval", "not_all_tracked")
        why[keep] = ""
        masks.append(_frozen(keep))
        reasons.append(_frozen(why))
        n_in += n
        n_kept += int(keep.sum())
        kept.append(s.select(keep))
    report = FilterReport("module2", n_in, n_kept, total, tuple(per_series), kept_iv.shape[0],
                          tuple(masks), tuple(reasons))
    return kept, kept_iv, report


@dataclass(frozen=True)
class RemovedMeasurements:
    """The measurements the filters removed, sorted by time, (M,) each: ``t`` (s), ``prism``,
    ``station``, ``xyz`` (M, 3; the raw measurement in the world frame, additive constant
    included, no atmospheric correction), ``stage`` (``"module1"``, ``"module2"``, ``"module4"``)
    and ``reason`` (a name of the stage's reasons)."""

    t: np.ndarray
    prism: np.ndarray
    station: np.ndarray
    xyz: np.ndarray
    stage: np.ndarray
    reason: np.ndarray

    def __len__(self) -> int:
        return self.t.shape[0]


def removed_measurements(
    observations: Sequence[Observations],
    module1_reports: Sequence[FilterReport],
    module2_masks: Sequence[np.ndarray],
    module2_reasons: Sequence[np.ndarray],
    transforms: Mapping[str, Any],
    outlier_masks: Sequence[np.ndarray] | None = None,
) -> RemovedMeasurements:
    """What modules 1 and 2 (and the windows of distance rejections, ``outlier_masks``) removed, in
    the world frame: from each station's raw ``observations``, its :func:`module1` report,
    :func:`module2`'s masks and reasons (indexed like module 1's kept measurements), the
    stations' ``transforms`` (with ``apply``) and the outlier masks (indexed like module 2's
    kept). Sorted by time, stably."""
    parts: dict[str, list] = {k: [] for k in ("t", "prism", "station", "xyz", "stage", "reason")}
    outliers = [None] * len(observations) if outlier_masks is None else outlier_masks
    for obs, rep, keep2, why2, out4 in zip(observations, module1_reports, module2_masks,
                                           module2_reasons, outliers, strict=True):
        keep1, why1 = rep.kept_masks[0], rep.reasons[0]
        if keep1.shape != (len(obs),) or np.shape(keep2) != (int(keep1.sum()),):
            raise ValueError(f"station {obs.station}: masks do not match its measurements")
        stage = np.where(keep1, "", "module1").astype(object)
        reason = np.asarray(why1, dtype=object).copy()
        kept1 = np.flatnonzero(keep1)
        gone2 = ~np.asarray(keep2, dtype=bool)
        stage[kept1[gone2]] = "module2"
        reason[kept1[gone2]] = np.asarray(why2)[gone2]
        if out4 is not None:
            kept2 = kept1[~gone2]
            if np.shape(out4) != kept2.shape:
                raise ValueError(f"station {obs.station}: outlier mask does not match its "
                                 "measurements")
            gone4 = kept2[np.asarray(out4, dtype=bool)]
            stage[gone4] = "module4"
            reason[gone4] = MODULE4_REASONS[0]
        gone = stage != ""
        if not gone.any():
            continue
        xyz = transforms[obs.station].apply(
            polar_to_cartesian(obs.hz[gone], obs.v[gone], obs.distance[gone]))
        m = int(gone.sum())
        parts["t"].append(np.asarray(obs.t[gone], dtype=float))
        parts["prism"].append(np.full(m, obs.prism, dtype=object))
        parts["station"].append(np.full(m, obs.station, dtype=object))
        parts["xyz"].append(xyz)
        parts["stage"].append(stage[gone])
        parts["reason"].append(reason[gone])
    if not parts["t"]:
        empty = np.empty(0, dtype=str)
        return RemovedMeasurements(np.empty(0), empty, empty, np.empty((0, 3)), empty, empty)
    out = {k: np.concatenate(v) for k, v in parts.items()}
    order = np.argsort(out["t"], kind="stable")
    return RemovedMeasurements(**{k: (v[order].astype(str) if v.dtype == object else v[order])
                                  for k, v in out.items()})


#: Share of a station's measurements that module 1 may reject for their rates before rtsgt
#: warns that the gates look too tight for the robot (outliers are rare; motion is not).
RATE_REJECTION_WARNING = 0.10


def warn_tight_rate_gates(obs: Observations, report, params: FilterParams) -> None:
    """Warn when module 1's rate gates removed more than :data:`RATE_REJECTION_WARNING` of a
    station's series: true motion of a fast or close robot, not outliers (docs/filtering.md#module-1).
    """
    n_rate = sum(int(report.removed.get(k, 0)) for k in ("rate_distance", "rate_hz", "rate_v"))
    if report.n_in and n_rate / report.n_in > RATE_REJECTION_WARNING:
        warnings.warn(
            f"station {obs.station}: module 1 rejected {n_rate} of {report.n_in} measurements "
            f"({100 * n_rate / report.n_in:.0f} %) for their rate of change (gates "
            f"tau_r = {params.tau_r:g} m/s, tau_a = {np.degrees(params.tau_a):g} deg/s, "
            f"tau_e = {np.degrees(params.tau_e):g} deg/s): that is motion, not outliers, if the "
            "robot is fast or close to the station; raise the [filter] gates of the "
            "configuration", RtsgtWarning, stacklevel=3)
