r"""Filtering modules 1 and 2 of Vaidis et al. (2022), "Accurate outdoor ground truth based on
total stations" (CRV 2021/2022), with the parameters of the paper (docs/filtering.md).

Module 1 (per station, on raw polar observations)
-------------------------------------------------
1. Observations with a non-zero instrument status or a non-finite value are removed
   (reasons ``"status"``, ``"non_finite"``), then those with a raw slope distance beyond
   ``max_distance`` (``"max_distance"``; the reference code's 1000 m); a measurement with the
   same time as the previous kept one is removed (``"duplicate_time"``); times going
   backwards are an input error.
2. The series is split into blocks at gaps **longer than** ``tau_s`` (``dt > tau_s``).
3. Each block starts at its **anchor**: its first measurement that agrees with at least one of
   the next :data:`ANCHOR_NEIGHBOURS` measurements of the block (passes the rate gates below
   against it). A measurement before the anchor disagrees with every one of them: it is
   rejected, with the reason of its first failing gate against the measurement that follows
   it. A measurement with fewer than two measurements after it in its block is not judged so
   (one neighbour cannot tell which of the two is wrong): it becomes the anchor. A wild first
   shot of a block thus costs one measurement, not the block; when the first measurement
   agrees with its neighbours, the anchor is the first measurement, as in the paper
   (docs/filtering.md#module-1).
4. After the anchor, every measurement is compared with the **last accepted** measurement of
   the same block (never with the previous block). It is rejected when the rate of change of
   the slope distance exceeds ``tau_r`` (``"rate_distance"``), else when the rate of change of
   the horizontal direction exceeds ``tau_a`` (``"rate_hz"``), else when that of the zenith
   angle exceeds ``tau_e`` (``"rate_v"``); rates are ``|difference| / dt`` and a rate equal to
   its threshold passes. The horizontal-direction difference is wrapped into ``[-pi, pi]``,
   so a crossing of 0 / 2 pi is not a jump. Comparing with the last accepted measurement
   (rather than with the previous raw one) means that one outlier removes one measurement,
   not also its successor.

The sequential rule is evaluated exactly without a Python loop over measurements: the anchors
are found from the gates of every measurement against its next neighbours at once, raw
consecutive pairs are tested at once, and only each episode that starts at a failing pair
(an outlier or a burst of them) is resolved, by a vectorised search for the first measurement
that agrees with the last accepted one again.

Module 2 (across prisms, on time series of each prism)
------------------------------------------------------
1. Each prism's series is split into segments at gaps longer than ``tau_s``.
2. The intervals where **every** prism is inside one of its segments are intersected
   (an interval ``[a, b]`` with ``a < b``, bounds being measurement times).
3. Intervals shorter than ``tau_l`` (``b - a < tau_l``) are dropped.
4. Each series keeps its measurements inside the kept intervals, **plus** the last measurement
   at or before ``a`` and the first at or after ``b`` of the segment that contains the interval,
   so that every time of ``[a, b]`` lies between two kept measurements of every prism (they are
   at most ``tau_s`` apart): an interpolator can then be queried on the whole interval.
   Removed measurements are counted as ``"short_interval"`` (inside an intersection interval
   dropped for its duration) or ``"not_all_tracked"`` (anywhere else).

Masks and reasons
-----------------
Both reports keep, for every series given, a boolean mask of what was kept and the reason of
each removal (``""`` when kept, else one of the names the counts use), indexed like the
input (:attr:`FilterReport.kept_masks`, :attr:`FilterReport.reasons`). From them,
:func:`removed_measurements` lists what the filters removed, in the world frame (the run
directory's ``measurements/removed.csv``), without filtering again.
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
#: before it becomes the block's anchor (module docstring, module 1 step 3).
ANCHOR_NEIGHBOURS = 3

#: Reasons of module 2.
MODULE2_REASONS = ("not_all_tracked", "short_interval")

#: Reason of the measurements module 4 leaves out of the GP fits: inside a window of poses
#: the distance gate rejected (:mod:`rtsgt.filtering.gates`).
MODULE4_REASONS = ("distance_window",)

_TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class FilterParams:
    """Thresholds of the filtering modules (defaults: Vaidis et al. 2022).

    Attributes
    ----------
    tau_r : float
        Largest rate of change of the slope distance, m/s (2 m/s).
    tau_a : float
        Largest rate of change of the horizontal direction, rad/s (1 deg/s).
    tau_e : float
        Largest rate of change of the zenith angle, rad/s (1 deg/s).
    tau_s : float
        Gap that splits a series, s (3 s): a gap longer than this starts a new block.
    tau_l : float
        Shortest interval kept by module 2, s (2 s).
    max_distance : float
        Largest raw slope distance module 1 keeps, m (:data:`DEFAULT_MAX_DISTANCE_M`).
    """

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
    """What a filtering module removed, and why.

    Attributes
    ----------
    module : str
        ``"module1"`` or ``"module2"``.
    n_in : int
        Number of measurements given (all series together).
    n_kept : int
        Number of measurements kept.
    removed : mapping str -> int
        Number removed for each reason (every reason of the module is present).
    per_series : tuple of mappings
        The same counts for each series given (module 2; module 1 has one series).
    n_blocks : int
        Module 1: blocks after splitting at gaps; module 2: intervals kept.
    kept_masks : tuple of ndarray of bool
        For each series given (module 1: one), shape (N_i,), indexed like its measurements:
        true where kept.
    reasons : tuple of ndarray of str
        For each series given, shape (N_i,): ``""`` where kept, else the reason of the removal
        (a key of ``removed``).
    """

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
    """Module 1 of Vaidis et al. (2022): rate gates on one station's observations.

    Parameters
    ----------
    obs : Observations
        Polar observations of one prism by one station (t s, hz rad, v rad, d m), in time
        order.
    params : FilterParams, optional
        Thresholds (default: the paper's).

    Returns
    -------
    kept : Observations
        The observations that pass, in the same order.
    report : FilterReport
        Counts per reason (module docstring), and the mask of what was kept and the reason of
        every removal, indexed like ``obs`` (``kept_masks[0]``, ``reasons[0]``).

    Raises
    ------
    InputError
        Times that go backwards.
    """
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
    """Module 2 of Vaidis et al. (2022): keep the intervals where every prism is tracked.

    Parameters
    ----------
    tracks : sequence of Observations or PrismTrack
        One time series per prism (usually three), each with strictly increasing times ``t``
        (s) on a common clock.
    params : FilterParams, optional
        ``tau_s`` and ``tau_l`` are used (default: the paper's).

    Returns
    -------
    kept : list
        The series restricted to the kept intervals (same types, same order), each with its
        bracketing measurements (module docstring).
    intervals : ndarray, shape (K, 2)
        Kept intervals ``[a, b]``, s, sorted and disjoint.
    report : FilterReport
        Counts per reason, total and per series, and per series the mask of what was kept and
        the reason of every removal (``kept_masks``, ``reasons``), indexed like its input.

    Raises
    ------
    InputError
        No series, or times not strictly increasing.
    """
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
    """The measurements that filtering modules 1 and 2 removed, sorted by time.

    Attributes
    ----------
    t : ndarray, shape (M,)
        Time, s.
    prism, station : ndarray of str, shape (M,)
    xyz : ndarray, shape (M, 3)
        The raw polar measurement (additive constant included, no atmospheric correction)
        mapped into the world frame by its station's calibration, m.
    stage : ndarray of str, shape (M,)
        ``"module1"`` or ``"module2"``: the module that removed it; ``"module4"``: left out of
        the GP fits as inside a window of poses the distance gate rejected
        (:mod:`rtsgt.filtering.gates`).
    reason : ndarray of str, shape (M,)
        Why: a name of :data:`MODULE1_REASONS` or :data:`MODULE2_REASONS`, or
        ``"distance_window"``.
    """

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
    """What modules 1 and 2 (and the windows of distance rejections) removed, from their masks,
    in the world frame.

    Parameters
    ----------
    observations : sequence of Observations
        The raw observations of each station, as given to :func:`module1`.
    module1_reports : sequence of FilterReport
        The report of :func:`module1` on each of them (same order).
    module2_masks, module2_reasons : sequences of ndarray
        For each station (same order), :func:`module2`'s mask and reasons of its series,
        indexed like the measurements module 1 kept.
    transforms : mapping str -> transform
        ``T_world_station`` of each station (an object with ``apply``).
    outlier_masks : sequence of ndarray of bool, optional
        For each station (same order), indexed like the measurements module 2 kept: true
        where left out of the GP fits as inside a window of distance rejections (stage
        ``"module4"``, reason ``"distance_window"``).

    Returns
    -------
    RemovedMeasurements
        One entry per removed measurement, sorted by time (stable: station order, then
        measurement order, for equal times).
    """
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
    """Warn when module 1's rate gates remove much of a station's series.

    The paper's gates (1 deg/s) suit a slow robot far from the stations; a robot at 2 m/s,
    10 m from a station, turns the line of sight by 11 deg/s, and the gates then reject true
    motion, not outliers: say so, with the numbers to change.
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
