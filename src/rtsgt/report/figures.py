"""The paper's figures for any run (matplotlib, Agg canvas, no pyplot state), PNG and SVG:
``source_norms`` (per-source ``sqrt(||Sigma_s||_F)`` by range bin against the paper's
medians, Vaidis et al. 2023, Fig. 4), ``pose_uncertainty`` (per source, translation and
rotation), ``top_view`` (the deployment from above with the 95 % ellipses, magnified) and
``uncertainty_time``. Boxes: median, quartiles, whiskers at the 5th and 95th percentiles.
Each function returns a :class:`DrawnFigure` saying what was drawn, for the tests.
docs/paper-figures.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from os import PathLike
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Ellipse, Patch
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from rtsgt.pose import register, shape_ratio
from rtsgt.record import RunRecord
from rtsgt.report.analysis import ALL, GP, REFERENCE, Analysis, paper_median_mm, pose_sigmas

__all__ = [
    "CHI2_2_95",
    "FIGURE_NAMES",
    "GAP_FACTOR",
    "DrawnFigure",
    "SOURCE_COLORS",
    "SOURCE_LABELS",
    "break_gaps",
    "draw_all",
    "plot_pose_uncertainty",
    "plot_source_norms",
    "plot_top_view",
    "plot_uncertainty_time",
    "save_figures",
]

#: chi-square(2) 0.95 quantile: the 95 % ellipse of a 2-D Gaussian is ``x^T S^-1 x <= 5.991``.
CHI2_2_95 = 5.991464547107979
#: Names (and file stems) of the figures, in report order.
FIGURE_NAMES = ("source_norms", "pose_uncertainty", "top_view", "uncertainty_time")
#: A time step longer than this multiple of the median step is a gap: lines drawn along time
#: (the ground-truth path, the evaluation's errors) break there (:func:`break_gaps`).
GAP_FACTOR = 3.0

#: Colour of each entry (colour-blind-safe Okabe-Ito palette).
SOURCE_COLORS = {
    "instrument": "#0072B2",
    "tilt": "#56B4E9",
    "atmosphere": "#009E73",
    "time_sync": "#E69F00",
    "calibration": "#D55E00",
    "correlated_noise": "#F0E442",
    GP: "#9467BD",
    REFERENCE: "#CC79A7",
    ALL: "#555555",
}
#: Readable names of the entries.
SOURCE_LABELS = {
    "instrument": "instrument",
    "tilt": "tilt compensator",
    "atmosphere": "atmosphere",
    "time_sync": "time synchronisation",
    "calibration": "extrinsic calibration",
    "correlated_noise": "time-correlated noise (inflation)",
    GP: "GP posterior (interpolation)",
    REFERENCE: "reference prisms (survey)",
    ALL: "all sources",
}
#: Shorter names for tick labels.
_SHORT_LABELS = {
    "tilt": "tilt",
    "time_sync": "time sync.",
    "calibration": "calibration",
    "correlated_noise": "correlated",
    GP: "GP posterior",
    REFERENCE: "reference survey",
}
_PRISM_COLORS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442")
_REASON_MARKERS = {"distance": "X", "uncertainty": "P", "degenerate": "v",
                   "missing_prism": "v", "collinear": "d"}
#: Markers and legend texts of the measurements removed by the filters, per module.
_STAGE_MARKERS = {"module1": "x", "module2": "1", "module4": "+"}
_STAGE_LABELS = {"module1": "measurements removed by module 1 (rates, status)",
                 "module2": "measurements removed by module 2 (not every prism tracked)",
                 "module4": "measurements left out of the GPs (windows of distance rejections)"}
_BOX_STYLE = dict(whis=(5, 95), showfliers=False, patch_artist=True, manage_ticks=False)


def _label(s: str) -> str:
    return SOURCE_LABELS.get(s, s.replace("_", " "))


def _color(s: str, k: int = 0) -> str:
    return SOURCE_COLORS.get(s, _PRISM_COLORS[k % len(_PRISM_COLORS)])


@dataclass
class DrawnFigure:
    """A figure and what was drawn on it, for the tests and the report: its ``name`` (one of
    :data:`FIGURE_NAMES`) and ``figure``; per panel the ``boxes``, their ``box_sizes`` (values
    behind each), ``box_keys`` (``(entry, group)``) and ``box_medians`` (read back from the
    artists); ``points`` per artist (by label or role); the ``ellipses`` and their
    ``ellipse_scale``; the shaded gaps per prism (``spans``) and of every prism
    (``common_spans``), counted once; a one-sentence ``caption``."""

    name: str
    figure: Figure
    boxes: dict[str, int] = field(default_factory=dict)
    box_sizes: dict[str, list[int]] = field(default_factory=dict)
    box_keys: dict[str, list[tuple]] = field(default_factory=dict)
    box_medians: dict[str, list[float]] = field(default_factory=dict)
    points: dict[str, int] = field(default_factory=dict)
    ellipses: int = 0
    ellipse_scale: float | None = None
    spans: int = 0
    common_spans: int = 0
    caption: str = ""

    def save(self, out_dir: str | PathLike, formats: Sequence[str] = ("png", "svg"),
             dpi: int = 150) -> list[Path]:
        """Write ``<out_dir>/<name>.<fmt>`` for each format; returns the paths."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        FigureCanvasAgg(self.figure)
        paths = []
        for fmt in formats:
            p = out / f"{self.name}.{fmt}"
            self.figure.savefig(p, format=fmt, dpi=dpi, bbox_inches="tight",
                                metadata={"Date": None} if fmt == "svg" else None)
            paths.append(p)
        return paths


def _box(ax, values: np.ndarray, x: float, width: float, color: str):
    bp = ax.boxplot([values], positions=[x], widths=width, **_BOX_STYLE)
    for patch in bp["boxes"]:
        patch.set_facecolor(color)
        patch.set_alpha(0.75)
        patch.set_edgecolor("black")
        patch.set_linewidth(0.8)
    for med in bp["medians"]:
        med.set_color("black")
        med.set_linewidth(1.2)
    return bp


def _plain_log(ax) -> None:
    """Plain numbers (0.1, 2, 50) instead of powers of ten on a log y axis.

    Minor ticks are labelled too when the axis spans less than about two decades.
    """

    fmt = FuncFormatter(lambda v, _: f"{v:.10g}")
    ax.yaxis.set_major_formatter(fmt)
    lo, hi = ax.get_ylim()
    decades = math.log10(max(hi, 1e-300) / max(lo, 1e-300))
    if decades < 1.3:
        ax.yaxis.set_minor_locator(LogLocator(subs=(2.0, 3.0, 5.0)))
        ax.yaxis.set_minor_formatter(fmt)
    elif decades < 2.3:
        ax.yaxis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
        ax.yaxis.set_minor_formatter(fmt)
    else:
        ax.yaxis.set_minor_formatter(NullFormatter())


def _positive(v: np.ndarray) -> np.ndarray:
    return v[np.isfinite(v) & (v > 0)]


def plot_source_norms(analysis: Analysis, *, show_paper: bool = True) -> DrawnFigure:
    """Per-source ``sqrt(||Sigma||_F)`` (mm) by range bin, with the share of measurements.

    One group of boxes per range bin that holds measurements, and a last group over all
    ranges; one box per entry of ``analysis.sources`` with positive values in the group. The
    paper's medians (:data:`rtsgt.report.analysis.PAPER_MEDIANS_MM`) are black diamonds at the
    groups for which the paper gives one.
    """
    a = analysis
    fig = Figure(figsize=(10, 6.4), layout="constrained")
    ax_share, ax = fig.subplots(2, 1, sharex=True, height_ratios=(1, 4))
    nb = len(a.bin_labels)
    groups = [k for k in range(nb) if a.bin_counts[k] > 0] + [nb]  # nb = all ranges
    ns = len(a.sources)
    width = 0.8 / ns
    edges = a.bin_edges_m
    drawn = DrawnFigure("source_norms", fig, box_sizes={"norms": []}, box_keys={"norms": []},
                        box_medians={"norms": []})
    paper_x, paper_y = [], []
    for gi, k in enumerate(groups):
        in_group = np.ones(a.n_measurements, bool) if k == nb else a.bin_index == k
        for si, s in enumerate(a.sources):
            vals = _positive(a.norm_mm[s][in_group])
            x = gi - 0.4 + width * (si + 0.5)
            if vals.size:
                bp = _box(ax, vals, x, width * 0.85, _color(s))
                drawn.box_medians["norms"].append(float(bp["medians"][0].get_ydata()[0]))
                drawn.box_sizes["norms"].append(int(vals.size))
                drawn.box_keys["norms"].append((s, "all ranges" if k == nb else a.bin_labels[k]))
            p = paper_median_mm(s) if k == nb else paper_median_mm(s, edges[k], edges[k + 1])
            if show_paper and p is not None:
                paper_x.append(x)
                paper_y.append(p)
    drawn.boxes["norms"] = len(drawn.box_sizes["norms"])
    if paper_x:
        ax.plot(paper_x, paper_y, "D", color="black", ms=5, mfc="white", mew=1.3, zorder=5)
        drawn.points["paper medians"] = len(paper_x)
    ax.set_yscale("log")
    ax.set_ylabel(r"$\sqrt{\|\Sigma\|_F}$ of the prism covariance (mm)")
    ticks = []
    for k in groups:
        if k == nb:
            ticks.append(f"all ranges\nn = {a.n_measurements}")
        else:
            ticks.append(f"{a.bin_labels[k]}\nn = {a.bin_counts[k]} "
                         f"({100 * a.bin_shares[k]:.0f} %)")
    ax.set_xticks(range(len(groups)), ticks)
    ax.set_xlim(-0.6, len(groups) - 0.4)
    empty = [a.bin_labels[k] for k in range(nb) if a.bin_counts[k] == 0]
    ax.set_xlabel("range from the station (m)" + (
        f"; no measurements in {', '.join(empty)}" if empty else ""))
    ax.grid(axis="y", which="both", alpha=0.3)
    handles = [Patch(facecolor=_color(s), edgecolor="black", alpha=0.75, label=_label(s))
               for s in a.sources]
    if paper_x:
        handles.append(Line2D([], [], marker="D", color="black", mfc="white", ls="",
                              label="paper median (Vaidis et al. 2023)"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
              framealpha=0.9)
    for gi in range(len(groups) - 1):
        ax.axvline(gi + 0.5, color="#bbbbbb", lw=0.8, ls="--" if gi == len(groups) - 2 else ":")
    _plain_log(ax)
    shares = [100 * a.bin_shares[k] for k in groups[:-1]]
    ax_share.bar(range(len(groups) - 1), shares, width=0.6, color="#999999")
    for x, v in enumerate(shares):
        ax_share.text(x, v, f"{v:.0f} %", ha="center", va="bottom", fontsize=8)
    ax_share.set_ylim(0, 115)
    ax_share.set_ylabel("share (%)")
    ax_share.set_title(f"{a.name}: size of each noise source at the prisms, by range "
                       "(boxes 25-75 %, whiskers 5-95 %)")
    drawn.points["share bars"] = len(shares)
    drawn.caption = (
        "Square root of the Frobenius norm of each noise source's 3x3 prism covariance (mm, "
        "log scale), by range bin and over all ranges; bars: share of the measurements per "
        "bin; diamonds: the paper's published medians.")
    return drawn


def plot_pose_uncertainty(analysis: Analysis) -> DrawnFigure:
    """Per-source pose uncertainty at the kept poses: translation (mm), rotation (mrad)."""
    a = analysis
    fig = Figure(figsize=(10, 4.8), layout="constrained")
    axes = fig.subplots(1, 2)
    drawn = DrawnFigure("pose_uncertainty", fig)
    for ax, (panel, data, unit) in zip(axes, (("translation", a.translation_mm, "mm"),
                                              ("rotation", a.rotation_mrad, "mrad")),
                                       strict=True):
        sizes, keys, labels, medians = [], [], [], []
        for s in a.pose_sources:
            vals = _positive(data[s])
            if not vals.size:
                continue
            x = len(sizes)
            bp = _box(ax, vals, x, 0.6, _color(s))
            medians.append(float(bp["medians"][0].get_ydata()[0]))
            sizes.append(int(vals.size))
            keys.append((s, panel))
            labels.append(_SHORT_LABELS.get(s, _label(s)))
            # the median, written above the upper whisker (clear of the box and its caps)
            ax.annotate(f"{np.median(vals):.3g}", (x, np.percentile(vals, 95)),
                        textcoords="offset points", xytext=(0, 3), fontsize=7.5,
                        ha="center", va="bottom")
        drawn.boxes[panel], drawn.box_sizes[panel], drawn.box_keys[panel] = \
            len(sizes), sizes, keys
        drawn.box_medians[panel] = medians
        ax.set_xticks(range(len(sizes)), labels, fontsize=8.5, rotation=30, ha="right",
                      rotation_mode="anchor")
        ax.set_xlim(-0.6, max(len(sizes), 1) - 0.4)
        if sizes:
            ax.set_yscale("log")
            lo, hi = ax.get_ylim()
            ax.set_ylim(lo, hi * (hi / lo) ** 0.06)  # room for the median labels on top
            _plain_log(ax)
        ax.set_ylabel(f"pose {panel} uncertainty ({unit})")
        ax.grid(axis="y", which="both", alpha=0.3)
    measure = ("sqrt(trace)" if a.pose_measure == "sqrt_trace"
               else "sqrt(largest eigenvalue)")
    fig.suptitle(f"{a.name}: pose uncertainty per noise source, {a.pose_t.size} kept poses "
                 f"({a.engine} engine; {measure} of each 3x3 block; labels: medians)",
                 fontsize=10)
    drawn.caption = (
        f"Uncertainty of the kept poses when only one source is present (prisms from that "
        f"source alone, reference exact; 'reference prisms' = the survey alone, prisms exact) "
        f"and with all of them (the run's covariance): {measure} of the translation block "
        f"(mm) and of the rotation block (mrad).")
    return drawn


def nice_scale(x: float) -> float:
    """Largest of 1, 2, 5 x 10^k not above ``x`` (at least 1)."""
    if not np.isfinite(x) or x <= 1:
        return 1.0
    k = math.floor(math.log10(x))
    for m in (5, 2, 1):
        if m * 10 ** k <= x:
            return float(m * 10 ** k)
    return float(10 ** k)  # pragma: no cover


def _ellipse_axes(cov2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full widths (major, minor) of the 95 % ellipses (m) and their angles (deg)."""
    w, V = np.linalg.eigh(cov2)
    w = np.clip(w, 0.0, None)
    major = 2 * np.sqrt(CHI2_2_95 * w[:, 1])
    minor = 2 * np.sqrt(CHI2_2_95 * w[:, 0])
    angle = np.degrees(np.arctan2(V[:, 1, 1], V[:, 0, 1]))
    return major, minor, angle


def break_gaps(t: np.ndarray, values: np.ndarray, factor: float = GAP_FACTOR) -> np.ndarray:
    """``values`` (N,) or (N, D) drawn at increasing times ``t`` (N,), s, with a NaN row inserted
    before each sample that follows a gap (a step over ``factor`` median steps), so that a line
    through them breaks: (N + G,) or (N + G, D)."""
    values = np.asarray(values, dtype=float)
    if t.size < 2:
        return values
    dts = np.diff(t)
    cut = np.flatnonzero(dts > factor * float(np.median(dts))) + 1
    return np.insert(values, cut, np.nan, axis=0)


def rejected_positions(data: RunRecord) -> tuple[np.ndarray, np.ndarray]:
    """Body positions of the rejected poses (fit of the reference onto the prisms), reasons.

    Rejected poses whose prisms are not all finite or nearly collinear are left out.
    """

    if data.rejected_t.size == 0 or data.prisms_t.size == 0:
        return np.empty((0, 3)), np.empty(0, dtype=str)
    idx = np.clip(np.searchsorted(data.prisms_t, data.rejected_t), 0, data.prisms_t.size - 1)
    prev = np.clip(idx - 1, 0, None)
    idx = np.where(np.abs(data.prisms_t[prev] - data.rejected_t)
                   < np.abs(data.prisms_t[idx] - data.rejected_t), prev, idx)
    match = np.abs(data.prisms_t[idx] - data.rejected_t) < 1e-6
    q = data.prisms_xyz[idx]
    ok = match & np.all(np.isfinite(q), axis=(1, 2))
    if ok.any():
        ok[ok] &= shape_ratio(q[ok]) >= 0.05
    if not ok.any():
        return np.empty((0, 3)), np.empty(0, dtype=str)
    _, t_body = register(np.broadcast_to(data.reference_xyz, q[ok].shape), q[ok])
    return t_body, data.rejected_reason[ok]


def body_origin_offset(data: RunRecord) -> float:
    """Distance of the body origin from the reference prisms' centroid, m."""
    r = np.asarray(data.reference_xyz, dtype=float)
    return float(np.linalg.norm(r.mean(axis=0))) if r.size else 0.0


def _label_offsets(xy: np.ndarray, dist: float = 22.0) -> np.ndarray:
    """Label offsets (points) pointing away from the centre of the labelled points.

    Points that are (nearly) at the centre get directions spread evenly around the circle, so
    that the labels of close stations do not overlap.
    """
    n = xy.shape[0]
    if n == 0:
        return np.empty((0, 2))
    d = xy - xy.mean(axis=0)
    spread = max(float(np.max(np.linalg.norm(d, axis=1))), 1e-12)
    ang = np.arctan2(d[:, 1], d[:, 0])
    near = np.linalg.norm(d, axis=1) < 0.2 * spread
    if n == 1 or near.all():
        ang = np.pi / 4 + 2 * np.pi * np.arange(n) / max(n, 1)
    else:
        ang = np.where(near, np.pi / 4 + 2 * np.pi * np.arange(n) / n, ang)
    return dist * np.column_stack([np.cos(ang), np.sin(ang)])


def plot_top_view(data: RunRecord, *, max_ellipses: int = 60,
                  ellipse_scale: float | None = None) -> DrawnFigure:
    """Top view of the deployment (world x-y, m), with 95 % ellipses at ``max_ellipses`` kept poses
    at most, magnified by ``ellipse_scale`` (default: the median about 1.5 % of the extent)."""
    fig = Figure(figsize=(9, 8), layout="constrained")
    ax = fig.subplots()
    drawn = DrawnFigure("top_view", fig)
    everything = []
    for k, (pid, tr) in enumerate(data.measurements.items()):
        xy = tr.xyz[:, :2]
        ax.plot(xy[:, 0], xy[:, 1], ".", ms=1.5, color=_PRISM_COLORS[k % len(_PRISM_COLORS)],
                alpha=0.6, label=f"prism {pid} measurements")
        drawn.points[f"prism {pid}"] = int(xy.shape[0])
        everything.append(xy)
    gt = data.groundtruth
    if len(gt):
        path = break_gaps(gt.t, gt.position[:, :2])
        lever = body_origin_offset(data)
        where = (f", {lever:.1f} m from the prisms' centroid" if lever >= 0.5 else "")
        ax.plot(path[:, 0], path[:, 1], "-", color="black", lw=1.0,
                label=f"ground truth (body origin{where})")
        drawn.points["ground truth"] = int(len(gt))
        everything.append(gt.position[:, :2])
    _top_view_stations(ax, data, everything)
    if data.stations:
        ax.plot([], [], "^", ms=9, color="#333333", mfc="#F0E442", label="stations")
        drawn.points["stations"] = len(data.stations)
    if data.gcp_xyz is not None and len(data.gcp_xyz):
        ax.plot(data.gcp_xyz[:, 0], data.gcp_xyz[:, 1], "s", ms=5, color="#666666",
                mfc="none", label="ground control points")
        drawn.points["ground control points"] = int(len(data.gcp_xyz))
        everything.append(data.gcp_xyz[:, :2])
    for stage in sorted(set(data.removed.stage.tolist())):
        m = data.removed.stage == stage
        ax.plot(data.removed.xyz[m, 0], data.removed.xyz[m, 1], _STAGE_MARKERS.get(stage, "x"),
                ms=4, ls="", color="#7F7F7F", mew=0.8,
                label=f"{_STAGE_LABELS.get(stage, stage)} ({int(m.sum())})")
        drawn.points[f"removed: {stage}"] = int(m.sum())
        everything.append(data.removed.xyz[m, :2])
    pos_r, reason_r = rejected_positions(data)
    for reason in sorted(set(reason_r.tolist())):
        m = reason_r == reason
        ax.plot(pos_r[m, 0], pos_r[m, 1], _REASON_MARKERS.get(reason, "x"), ms=6, ls="",
                color="#D55E00", mfc="none", label=f"rejected: {reason or 'unspecified'} "
                f"({int(m.sum())})")
        drawn.points[f"rejected: {reason}"] = int(m.sum())
    extent = 1.0
    if everything:
        allxy = np.concatenate(everything)
        allxy = allxy[np.all(np.isfinite(allxy), axis=1)]
        if allxy.size:
            extent = max(float(np.ptp(allxy[:, 0])), float(np.ptp(allxy[:, 1])), 1.0)
    if len(gt) and gt.cov is not None and max_ellipses > 0:
        _top_view_ellipses(ax, drawn, gt, extent, max_ellipses, ellipse_scale)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x, world frame (m)")
    ax.set_ylabel("y, world frame (m)")
    ax.grid(alpha=0.3)
    leg = ax.legend(loc="best", fontsize=8, framealpha=0.9)
    for h in leg.legend_handles:  # the measurement dots are tiny on the map, not in the key
        if isinstance(h, Line2D) and h.get_marker() == ".":
            h.set_markersize(8)
    ax.set_title(f"{data.name}: top view (world frame = reference station)")
    scale_txt = ("" if drawn.ellipse_scale is None else
                 f"; 95 % horizontal ellipses magnified {drawn.ellipse_scale:g} times")
    lever = body_origin_offset(data)
    lever_txt = (f" (the body origin is {lever:.1f} m from the prisms' centroid: the path "
                 f"is that point's)" if lever >= 0.5 else "")
    drawn.caption = ("Top view of the deployment: stations, ground control points, measured "
                     "prism positions, ground-truth path" + lever_txt + scale_txt +
                     ", measurements removed by the filters (by module) and poses rejected "
                     "by the gates (by gate).")
    return drawn


def _top_view_stations(ax, data: RunRecord, everything: list) -> None:
    """The stations, labelled beside their markers, on the top view."""
    offsets = _label_offsets(np.array([p[:2] for p in data.stations.values()]).reshape(-1, 2))
    for (s, p), off in zip(data.stations.items(), offsets, strict=True):
        ax.plot(p[0], p[1], "^", ms=11, color="#333333", mfc="#F0E442", mew=1.2)
        ax.annotate(f"station {s}", (p[0], p[1]), textcoords="offset points",
                    xytext=tuple(off), fontsize=9, fontweight="bold",
                    ha="left" if off[0] >= 0 else "right",
                    va="bottom" if off[1] >= 0 else "top",
                    bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8),
                    arrowprops=dict(arrowstyle="-", color="#555555", lw=0.6))
        everything.append(p[None, :2])


def _top_view_ellipses(ax, drawn: DrawnFigure, gt, extent: float, max_ellipses: int,
                       ellipse_scale: float | None) -> None:
    """The 95 % horizontal ellipses of at most ``max_ellipses`` kept poses on the top view,
    magnified by ``ellipse_scale`` (default: the median 1.5 % of ``extent``)."""
    ok = np.flatnonzero(np.all(np.isfinite(gt.cov[:, :2, :2]), axis=(1, 2)))
    if ok.size:
        sel = ok[np.unique(np.linspace(0, ok.size - 1, min(ok.size, max_ellipses))
                           .round().astype(int))]
        major, minor, angle = _ellipse_axes(gt.cov[sel, :2, :2])
        if ellipse_scale is None:
            med = float(np.median(major))
            ellipse_scale = nice_scale(0.015 * extent / med) if med > 0 else 1.0
        for (x, y), w, h, ang in zip(gt.position[sel, :2], major, minor, angle,
                                     strict=True):
            ax.add_patch(Ellipse((x, y), w * ellipse_scale, h * ellipse_scale, angle=ang,
                                 fc="#0072B2", ec="#0072B2", alpha=0.35, lw=0.8))
        drawn.ellipses = int(sel.size)
        drawn.ellipse_scale = float(ellipse_scale)
        ax.plot([], [], "o", ms=9, color="#0072B2", alpha=0.35,
                label=f"95 % position ellipses x {ellipse_scale:g} ({sel.size} poses)")


def _gaps(t: np.ndarray, gap_s: float) -> list[tuple[float, float]]:
    if t.size < 2:
        return []
    d = np.diff(t)
    k = np.flatnonzero(d > gap_s)
    return [(float(t[i]), float(t[i + 1])) for i in k]


def _intersect_intervals(sets: list[np.ndarray]) -> np.ndarray:
    """Intervals covered by every set of disjoint ``(start, end)`` intervals, shape (K, 2)."""
    out = sets[0]
    for other in sets[1:]:
        lo = np.maximum(out[:, None, 0], other[None, :, 0])
        hi = np.minimum(out[:, None, 1], other[None, :, 1])
        keep = hi > lo
        out = np.column_stack([lo[keep], hi[keep]])
        out = out[np.argsort(out[:, 0])] if out.size else out.reshape(0, 2)
    return out


def default_gap_s(data: RunRecord) -> float:
    """Gap threshold: three times the median measurement interval, at least 1 s."""
    dts = [np.diff(tr.t) for tr in data.measurements.values() if len(tr) > 1]
    med = float(np.median(np.concatenate(dts))) if dts else 0.4
    return max(1.0, 3.0 * med)


def _time_origin(data: RunRecord) -> float:
    starts = [tr.t[0] for tr in data.measurements.values() if len(tr)]
    if data.prisms_t.size:
        starts.append(data.prisms_t[0])
    return float(min(starts)) if starts else 0.0


def _time_label(t0: float) -> str:
    if t0 > 1e8:
        iso = datetime.fromtimestamp(t0, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
        return f"time since {iso} (s)"
    return f"time since t = {t0:g} s (s)"


def _shade_gaps(axes, data: RunRecord, gap: float, t0: float, drawn: DrawnFigure) -> None:
    """Shade each prism's measurement gaps longer than ``gap`` s in its colour on every panel,
    and those of every prism in one neutral grey; counted in ``drawn``."""
    n_spans = 0
    all_gaps = []
    for i, (pid, tr) in enumerate(data.measurements.items()):
        col = _PRISM_COLORS[i % 7]
        g = _gaps(tr.t, gap)
        all_gaps.append(np.asarray(g, dtype=float).reshape(-1, 2))
        for a, b in g:
            for ax in axes:
                ax.axvspan(a - t0, b - t0, color=col, alpha=0.15, lw=0, zorder=0.4)
            n_spans += 1
        axes[0].plot([], [], "s", ms=9, color=col, alpha=0.3,
                     label=f"prism {pid}: gap > {gap:.1f} s")
    drawn.spans = n_spans
    common = _intersect_intervals(all_gaps) if len(all_gaps) > 1 else np.empty((0, 2))
    for a, b in common:
        for ax in axes:
            ax.axvspan(a - t0, b - t0, color="#d4d4d4", alpha=0.95, lw=0, zorder=0.5)
    if common.shape[0]:
        axes[0].plot([], [], "s", ms=9, color="#d4d4d4", label="no prism measured")
    drawn.common_spans = int(common.shape[0])


def plot_uncertainty_time(data: RunRecord, *, gap_s: float | None = None,
                          pose_measure: str = "sqrt_trace") -> DrawnFigure:
    """Uncertainty along time: ``sqrt(tr Sigma)`` of each interpolated prism (mm), the pose's
    translation (mm) and rotation (mrad) (``pose_measure``); measurement gaps over ``gap_s``
    (default :func:`default_gap_s`) shaded, rejected poses ticked."""
    fig = Figure(figsize=(11, 8), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    drawn = DrawnFigure("uncertainty_time", fig)
    t0 = _time_origin(data)
    gap = default_gap_s(data) if gap_s is None else float(gap_s)
    for i, pid in enumerate(data.prism_ids):
        c = data.prisms_cov[:, i]
        sig = np.sqrt(np.clip(np.trace(c, axis1=-2, axis2=-1), 0.0, None)) * 1e3
        y = break_gaps(data.prisms_t, np.column_stack([data.prisms_t - t0, sig]), 2.5)
        axes[0].plot(y[:, 0], y[:, 1], "-", lw=1.0, color=_PRISM_COLORS[i % 7],
                     label=f"prism {pid}")
        drawn.points[f"prism {pid}"] = int(np.count_nonzero(np.isfinite(sig)))
    gt = data.groundtruth
    if len(gt) and gt.cov is not None:
        tr_mm, rot_mrad = pose_sigmas(gt.cov, pose_measure)
        for ax, v, name in ((axes[1], tr_mm, "pose translation"),
                            (axes[2], rot_mrad, "pose rotation")):
            y = break_gaps(gt.t, np.column_stack([gt.t - t0, v]), 2.5)
            ax.plot(y[:, 0], y[:, 1], "-", lw=1.0, color="black", label=name)
            drawn.points[name] = int(np.count_nonzero(np.isfinite(v)))
    for stage in sorted(set(data.removed.stage.tolist())):
        m = data.removed.stage == stage
        axes[0].plot(data.removed.t[m] - t0, np.zeros(int(m.sum())), "|", ms=12, mew=1.2,
                     color="#7F7F7F" if stage == "module2" else "#000000",
                     transform=axes[0].get_xaxis_transform(), clip_on=False,
                     label=f"removed by {stage.replace('module', 'module ')} "
                           f"({int(m.sum())})")
        drawn.points[f"removed: {stage}"] = int(m.sum())
    if data.rejected_t.size:
        axes[1].plot(data.rejected_t - t0, np.zeros(data.rejected_t.size), "|", ms=16,
                     mew=2, color="#D55E00", transform=axes[1].get_xaxis_transform(),
                     label=f"rejected poses ({data.rejected_t.size})")
        drawn.points["rejected poses"] = int(data.rejected_t.size)
    _shade_gaps(axes, data, gap, t0, drawn)
    unit = "sqrt(trace)" if pose_measure == "sqrt_trace" else "sqrt(largest eigenvalue)"
    axes[0].set_ylabel("prism sqrt(tr Σ) (mm)")
    axes[1].set_ylabel(f"translation {unit}\n(mm)")
    axes[2].set_ylabel(f"rotation {unit}\n(mrad)")
    for ax in axes:
        if ax.lines and any(np.nanmax(np.asarray(ln.get_ydata(), dtype=float), initial=0) > 0
                            for ln in ax.lines if len(ln.get_ydata())):
            ax.set_yscale("log")
            _plain_log(ax)
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, framealpha=0.9)
    axes[-1].set_xlabel(_time_label(t0))
    axes[0].set_title(f"{data.name}: uncertainty along time (shaded: measurement gaps)")
    drawn.caption = (f"Uncertainty along time: each interpolated prism (mm), the pose "
                     f"translation (mm) and rotation (mrad); shaded: gaps longer than "
                     f"{gap:.1f} s between two measurements of a prism (grey: of every prism); "
                     f"ticks: rejected poses.")
    return drawn


def draw_all(data: RunRecord, analysis: Analysis, **kwargs) -> dict[str, DrawnFigure]:
    """The four figures, keyed by :data:`FIGURE_NAMES`."""
    return {
        "source_norms": plot_source_norms(analysis),
        "pose_uncertainty": plot_pose_uncertainty(analysis),
        "top_view": plot_top_view(data, **kwargs),
        "uncertainty_time": plot_uncertainty_time(data, pose_measure=analysis.pose_measure),
    }


def save_figures(figures: dict[str, DrawnFigure], out_dir: str | PathLike,
                 formats: Sequence[str] = ("png", "svg"), dpi: int = 150) -> list[Path]:
    """Write every figure as ``<name>.<fmt>`` into ``out_dir``; returns the paths."""
    paths: list[Path] = []
    for fig in figures.values():
        paths += fig.save(out_dir, formats, dpi)
    return paths
