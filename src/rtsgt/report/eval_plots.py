"""Figures of ``rtsgt evaluate --plot DIR`` (matplotlib, Agg canvas, no pyplot state).

PNG and SVG of ``translation_error`` (APE norm and x, y, z against the ground truth's sigma
bands), ``top_view`` (x-y paths with magnified 95 % ellipses), ``nees_histogram`` (against the
chi-square densities) and ``drift`` (by segment length); lines break at gaps longer than
:data:`rtsgt.report.figures.GAP_FACTOR` median steps; a text box gives the mounting and clock
when the estimate was moved by one. docs/evaluating.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse
from scipy import stats

from rtsgt.io.output_dir import OutputDir
from rtsgt.report.figures import break_gaps

#: chi-square(2) 0.95 quantile: the 95 % ellipse of a 2-D Gaussian.
CHI2_2_95 = float(stats.chi2.ppf(0.95, 2))


@dataclass(frozen=True)
class EvalPlots:
    """What :func:`plot_evaluation` drew (for the tests): ``files``, ``n_ellipses``,
    ``ellipse_scale``, ``sigma_norm`` (N,) and ``sigma_xyz`` (N, 3) m, ``hist`` {"position",
    "pose": (counts, edges)}, ``mounting_text``, ``drift`` {(kind, part): (lengths, mean, floor)}.
    """

    files: list[Path]
    n_ellipses: int
    ellipse_scale: float
    sigma_norm: np.ndarray | None
    sigma_xyz: np.ndarray | None
    hist: dict = field(default_factory=dict)
    mounting_text: str | None = None
    drift: dict = field(default_factory=dict)


def _pm(value: str, sigma: float | None, fmt: str) -> str:
    return value if sigma is None or not np.isfinite(sigma) else f"{value} +- {sigma:{fmt}}"


def mounting_text(result) -> str | None:
    """The mounting ``T_body_sensor`` and the clock offset of ``result``, one line each, with
    ``+- sigma`` for what was estimated (None when the estimate was not moved by a mounting)."""
    m = getattr(result, "mounting", None)  # a position-only evaluation has a lever arm instead
    if m is None:
        return None
    rv = m.rotation_vector
    angle = float(np.linalg.norm(rv))
    axis = rv / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    rs, ls, cs = (m.group_sigma(g) for g in ("rotation", "lever", "clock"))
    rot = f"rotation {np.degrees(angle):.3f} deg about ({axis[0]:.3f}, {axis[1]:.3f}, {axis[2]:.3f})"
    if rs is not None:
        rot += f" +- ({', '.join(f'{np.degrees(v):.3f}' for v in rs)}) deg"
    lev = "lever arm (" + ", ".join(
        _pm(f"{1e3 * v:.1f}", None if ls is None else 1e3 * ls[k], ".1f")
        for k, v in enumerate(m.lever)) + ") mm"
    clk = "clock offset " + _pm(f"{1e3 * m.clock_offset:.3f}",
                                None if cs is None else 1e3 * cs[0], ".3f") + " ms"
    head = ("T_body_sensor estimated: " + ", ".join(m.estimated) if m.estimated
            else "T_body_sensor given")
    return "\n".join([head, rot, lev, clk])


def _text_box(ax, text: str | None) -> None:
    if text:
        ax.text(0.01, 0.01, text, transform=ax.transAxes, fontsize="x-small", va="bottom",
                ha="left", family="monospace",
                bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.8})


def _save(fig: Figure, out: Path, name: str, files: list[Path]) -> None:
    FigureCanvasAgg(fig)
    for ext in ("png", "svg"):
        p = out / f"{name}.{ext}"
        fig.savefig(p, format=ext, dpi=120, bbox_inches="tight")
        files.append(p)


def _error_figure(result) -> tuple[Figure, np.ndarray | None, np.ndarray | None]:
    """The error figure; its lines and bands break at the gaps between associated poses
    (:func:`rtsgt.report.figures.break_gaps`)."""
    t = result.t - result.t[0]
    err = result.est.position - result.gt.position
    fig = Figure(figsize=(9, 9))
    axes = fig.subplots(4, 1, sharex=True)
    sig_norm = sig_xyz = None
    cov = result.gt.cov
    if cov is not None:
        sig_xyz = np.sqrt(np.clip(np.diagonal(cov[:, :3, :3], axis1=1, axis2=2), 0, None))
        sig_norm = np.sqrt(np.clip(np.trace(cov[:, :3, :3], axis1=1, axis2=2), 0, None))
    tb = break_gaps(result.t, t)
    ax = axes[0]
    ax.plot(tb, break_gaps(result.t, 1e3 * np.linalg.norm(err, axis=1)), color="k", lw=0.8,
            label="|error|")
    if sig_norm is not None:
        for k, ls in zip((1, 2, 3), ("-", "--", ":"), strict=True):
            ax.plot(
                tb,
                break_gaps(result.t, 1e3 * k * sig_norm),
                color="tab:red",
                ls=ls,
                lw=0.8,
                label=f"{k} x rms ground-truth noise",
            )
    ax.set_ylabel("APE translation (mm)")
    ax.legend(loc="upper right", fontsize="small")
    _text_box(ax, mounting_text(result))
    for a, (ax, name) in enumerate(zip(axes[1:], "xyz", strict=True)):
        if sig_xyz is not None:
            for k, alpha in zip((3, 2, 1), (0.12, 0.2, 0.3), strict=True):
                s = break_gaps(result.t, 1e3 * k * sig_xyz[:, a])
                ax.fill_between(tb, -s, s, color="tab:blue", alpha=alpha, lw=0,
                                label=f"+-{k} sigma ground truth")
        ax.plot(tb, break_gaps(result.t, 1e3 * err[:, a]), color="k", lw=0.8,
                label=f"error {name}")
        ax.set_ylabel(f"{name} error (mm)")
    axes[1].legend(loc="upper right", fontsize="small")
    axes[-1].set_xlabel("time since first associated pose (s)")
    fig.suptitle("Translation error against the ground truth's uncertainty")
    return fig, sig_norm, sig_xyz


def _ellipse_params(cov2: np.ndarray, k2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full widths, heights (m) and angles (deg) of ``x^T C^-1 x = k2`` ellipses, (N, 2, 2)."""
    w, v = np.linalg.eigh(cov2)
    w = np.clip(w, 0, None)
    width = 2 * np.sqrt(k2 * w[:, 1])
    height = 2 * np.sqrt(k2 * w[:, 0])
    angle = np.degrees(np.arctan2(v[:, 1, 1], v[:, 0, 1]))
    return width, height, angle


def _top_view(result, max_ellipses: int, ellipse_scale: float | None) -> tuple[Figure, int, float]:
    gt, est = result.gt.position, break_gaps(result.t, result.est.position)
    fig = Figure(figsize=(7, 7))
    ax = fig.subplots()
    path = break_gaps(result.t, gt)
    ax.plot(path[:, 0], path[:, 1], color="k", lw=1.0, label="ground truth")
    ax.plot(
        est[:, 0],
        est[:, 1],
        color="tab:orange",
        lw=0.8,
        label=f"estimate ({result.alignment.method})",
    )
    n_ell, scale = 0, 1.0
    if result.gt.cov is not None and max_ellipses > 0:
        idx = np.unique(np.linspace(0, len(gt) - 1, min(max_ellipses, len(gt))).astype(int))
        wdt, hgt, ang = _ellipse_params(result.gt.cov[idx, :2, :2], CHI2_2_95)
        if ellipse_scale is None:
            extent = float(np.ptp(gt[:, :2], axis=0).max()) or 1.0
            med = float(np.median(wdt)) or extent
            # make the median ellipse about 2 % of the trajectory extent, rounded to 1-2-5
            raw = max(1.0, 0.02 * extent / med)
            dec = 10 ** np.floor(np.log10(raw))
            scale = float(min(m * dec for m in (1, 2, 5, 10) if m * dec >= raw))
        else:
            scale = float(ellipse_scale)
        for k, i in enumerate(idx):
            ax.add_patch(
                Ellipse(
                    (gt[i, 0], gt[i, 1]),
                    scale * wdt[k],
                    scale * hgt[k],
                    angle=ang[k],
                    fill=False,
                    color="tab:blue",
                    lw=0.7,
                    label=f"95 % ground-truth ellipse x {scale:g}" if k == 0 else None,
                )
            )
        n_ell = idx.size
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize="small")
    _text_box(ax, mounting_text(result))
    ax.set_title("Top view")
    return fig, n_ell, scale


def _nees_figure(result) -> tuple[Figure, dict]:
    fig = Figure(figsize=(10, 4))
    axes = fig.subplots(1, 2)
    hist = {}
    for ax, (name, r) in zip(
        axes, (("position", result.nees.position), ("pose", result.nees.pose)), strict=True
    ):
        if r is None:
            positions_only = name == "pose" and hasattr(result, "lever_arm")
            ax.text(
                0.5,
                0.5,
                "position-only ground truth:\nrotations not reported" if positions_only
                else "no ground-truth covariance",
                ha="center",
                va="center",
                transform=ax.transAxes,
            )
            continue
        top = max(float(np.quantile(r.values, 0.99)), 3 * r.quantile_95)
        edges = np.linspace(0, top, 41)
        counts, edges, _ = ax.hist(
            np.clip(r.values, 0, top),
            bins=edges,
            density=True,
            color="tab:blue",
            alpha=0.6,
            label=f"NEES ({r.n} poses)",
        )
        x = np.linspace(1e-6, top, 400)
        ax.plot(x, stats.chi2.pdf(x, r.dof), color="k", lw=1.2, label=f"chi-square({r.dof})")
        ax.axvline(
            r.quantile_95,
            color="tab:red",
            ls="--",
            lw=1,
            label=f"95 % quantile {r.quantile_95:.3f}",
        )
        verdict = "consistent" if r.consistent else "inconsistent"
        ax.set_title(
            f"{name}: mean {r.mean:.2f} (dof {r.dof}), "
            f"{100 * r.fraction_inside_95:.1f} % inside, {verdict}",
            fontsize="medium",
        )
        ax.set_xlabel("NEES")
        ax.legend(fontsize="small")
        hist[name] = (np.asarray(counts), np.asarray(edges))
    return fig, hist


#: The drift panels: (kind, part) -> (scale of the stored value, y label, x label).
DRIFT_PANELS = {
    ("distance", "translation"): (100.0, "translational drift (%)", "segment length (m of path)"),
    ("distance", "rotation"): (float(np.degrees(1.0)), "rotational drift (deg/m)",
                               "segment length (m of path)"),
    ("time", "translation"): (1e3, "translational drift (mm/s)", "segment length (s)"),
    ("time", "rotation"): (float(np.degrees(1.0)), "rotational drift (deg/s)",
                           "segment length (s)"),
}


def _drift_panel(ax, seg, part: str, scale: float) -> tuple | None:
    """One panel: every segment's drift (grey), each length's mean, the ground truth's floor;
    returns (lengths, mean, floor) as drawn, None when there is nothing to draw."""
    per_seg = getattr(seg, f"{part}_error")
    if per_seg is None or seg.segments.first.size == 0:
        return None
    lengths = seg.lengths
    x = lengths[seg.segments.which]
    ax.plot(x, scale * per_seg, ".", color="0.7", ms=2, label="segments")
    mean = scale * getattr(seg, part)
    ax.plot(lengths, mean, "o-", color="k", lw=1.0, label="mean (KITTI)")
    floor = getattr(seg, f"{part}_floor")
    if floor is not None:
        floor = scale * floor
        ax.plot(lengths, floor, "--", color="tab:red", lw=1.0,
                label="ground truth's floor (rms)")
    ax.set_yscale("log")
    ax.legend(fontsize="x-small")
    return lengths, mean, floor


def _drift_figure(result) -> tuple[Figure, dict]:
    """The drift figure (module docstring) and what each panel drew."""
    drift = getattr(result, "drift", None)
    fig = Figure(figsize=(10, 7))
    axes = fig.subplots(2, 2)
    drawn = {}
    for (kind, part), ax in zip(DRIFT_PANELS, axes.ravel(), strict=True):
        scale, ylabel, xlabel = DRIFT_PANELS[(kind, part)]
        seg = None if drift is None else getattr(drift, kind)
        out = None if seg is None else _drift_panel(ax, seg, part, scale)
        if out is None:
            why = ("rotational drift not estimable:\nposition-only ground truth"
                   if part == "rotation" and drift is not None and drift.rotation
                   else "no segment")
            ax.text(0.5, 0.5, why, ha="center", va="center", transform=ax.transAxes)
        else:
            drawn[(kind, part)] = out
            if kind == "time":
                ax.set_xscale("log")
        ax.set_ylabel(ylabel)
        ax.set_xlabel(xlabel)
    fig.suptitle("Drift by segment length against the ground truth's own")
    return fig, drawn


def plot_evaluation(
    result,
    out_dir: str | PathLike,
    *,
    max_ellipses: int = 60,
    ellipse_scale: float | None = None,
    force: bool = False,
) -> EvalPlots:
    """Write the evaluation figures into ``out_dir``, whole or not at all (an earlier rtsgt output
    replaced only with ``force``); ``max_ellipses`` on the top view, ``ellipse_scale`` (None:
    1-2-5 automatic). A position result draws its tracked point. Returns :class:`EvalPlots`.
    """
    output = OutputDir(out_dir, "evaluation plots", force=force)
    with output as tmp:
        files: list[Path] = []
        fig, sig_norm, sig_xyz = _error_figure(result)
        _save(fig, tmp, "translation_error", files)
        fig, n_ell, scale = _top_view(result, max_ellipses, ellipse_scale)
        _save(fig, tmp, "top_view", files)
        fig, hist = _nees_figure(result)
        _save(fig, tmp, "nees_histogram", files)
        fig, drift = _drift_figure(result)
        _save(fig, tmp, "drift", files)
    files = [output.final / p.name for p in files]
    return EvalPlots(files, n_ell, scale, sig_norm, sig_xyz, hist, mounting_text(result),
                     drift)
