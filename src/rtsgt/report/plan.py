"""What ``rtsgt plan`` writes: the map (:func:`draw_plan_map`: the predicted sigma over the
area or the path, the stations with the :data:`~rtsgt.planning.plan.RANGE_LIMIT_M` circle,
the markers and their hull; two plans side by side with one colour scale), the table,
``plan.json`` and the HTML section (:func:`plan_section_html`, :func:`render_plan_page`).
Reads no file. docs/planning.md.
"""

from __future__ import annotations

import html
import json
from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon

from rtsgt import __version__
from rtsgt.io._parse import table_text
from rtsgt.planning.plan import RANGE_LIMIT_M, PlanResult, horizontal_hull
from rtsgt.report.figures import DrawnFigure
from rtsgt.report.html import figure_html
from rtsgt.report.style import CSS

__all__ = ["PLAN_SCHEMA_NAME", "PLAN_SCHEMA_VERSION", "draw_plan_map", "plan_document",
           "plan_json_text", "plan_section_html", "plan_table_text", "render_plan_page"]

PLAN_SCHEMA_NAME = "rtsgt-plan"
PLAN_SCHEMA_VERSION = 1
_CMAP = "viridis"


def plan_table_text(result: PlanResult) -> str:
    """The prediction at every point as CSV: ``[t,]x,y,z,sigma_mm,sigma_worst_mm,
    rotation_mrad,max_range_m`` (plan coordinates; ``sigma_mm`` the median over the headings,
    ``sigma_worst_mm`` the largest; NaN where not predicted)."""
    rot = np.full(result.points.shape[0], np.nan)
    ok = np.any(np.isfinite(result.rotation_sigma_rad), axis=1)
    rot[ok] = np.nanmedian(result.rotation_sigma_rad[ok], axis=1)
    cols = [result.points, 1e3 * result.sigma_median_m[:, None],
            1e3 * result.sigma_worst_m[:, None], 1e3 * rot[:, None], result.max_range_m[:, None]]
    header = "x,y,z,sigma_mm,sigma_worst_mm,rotation_mrad,max_range_m"
    if result.t is not None:
        cols.insert(0, result.t[:, None])
        header = "t," + header
    return table_text(np.hstack(cols), header=header)


def _layout_dict(result: PlanResult) -> dict:
    lay = result.layout
    xyz = lay.station_xyz()
    tracked = dict(zip(lay.stations, zip(lay.prisms, lay.rate_hz, strict=True), strict=True))
    stations = {}
    for s, p in xyz.items():
        T = lay.calibration.transforms[s]
        entry = {"xyz_m": [float(v) for v in p]}
        if s in tracked:
            entry["prism"], entry["rate_hz"] = tracked[s][0], float(tracked[s][1])
        if T.covariance is not None:
            entry["calibration_sigma_translation_mm"] = [
                float(v) for v in np.sqrt(np.diag(T.covariance)[:3]) * 1e3]
            entry["calibration_sigma_rotation_mrad"] = [
                float(v) for v in np.sqrt(np.diag(T.covariance)[3:]) * 1e3]
        stations[s] = entry
    opt = lay.options
    return {
        "source": lay.source,
        "reference_station": lay.calibration.reference_station,
        "origin_m": [float(v) for v in lay.origin],
        "stations": stations,
        "gcp": {n: [float(v) for v in p + lay.origin]
                for n, p in zip(lay.gcp_names, lay.gcp_xyz, strict=True)},
        "rig": {"names": list(lay.reference.names),
                "xyz_m": lay.reference.xyz.tolist(),
                "sigma_m": [float(v) for v in np.sqrt(np.diag(lay.reference.cov))]},
        "instrument": lay.instrument.name,
        "noise_sources": list(lay.model.sources),
        "calibration_model": opt.calibration.model,
        "calibration_samples": opt.pose.samples,
        "seed": opt.seed,
        "registration": opt.pose.registration,
        "gp_noise": opt.interpolation.gp_noise,
    }


def plan_document(results: Sequence[PlanResult], inputs: Sequence[str]) -> dict:
    """``plan.json``: one entry per plan (the first is the plan, the second the one it is
    compared with), each with its layout, the robot's motion, the engine's settings, the
    summary of the prediction and the advice."""
    plans = []
    for res, src in zip(results, inputs, strict=True):
        plans.append({"name": res.name, "input": src, "layout": _layout_dict(res),
                      "robot": res.motion.to_dict(),
                      "engine": "linear (noise model, GP on a stationary track, registration)",
                      "prediction": res.summary()})
    return {"schema": {"name": PLAN_SCHEMA_NAME, "version": PLAN_SCHEMA_VERSION},
            "software": {"name": "rtsgt", "version": __version__}, "plans": plans}


def plan_json_text(results: Sequence[PlanResult], inputs: Sequence[str]) -> str:
    """:func:`plan_document` as text (NaN written as null)."""
    def clean(x):
        if isinstance(x, float) and not np.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x
    return json.dumps(clean(plan_document(results, inputs)), indent=1) + "\n"


def _norm(results: Sequence[PlanResult]) -> Normalize:
    vals = np.concatenate([r.sigma_median_m for r in results]) * 1e3
    vals = vals[np.isfinite(vals)]
    if not vals.size:
        return Normalize(0.0, 1.0)
    lo, hi = float(vals.min()), float(vals.max())
    return Normalize(lo, hi if hi > lo else lo + 1e-3)


def _panel(ax, res: PlanResult, norm: Normalize):
    lay = res.layout
    sig = res.sigma_median_m * 1e3
    if res.kind == "area":
        Z = np.full(res.grid_mask.shape, np.nan)
        Z[res.grid_mask] = sig
        im = ax.pcolormesh(res.grid_x, res.grid_y, np.ma.masked_invalid(Z), shading="nearest",
                           cmap=_CMAP, norm=norm)
        ax.add_patch(Polygon(res.polygon, closed=True, fill=False, lw=0.8, ec="0.3"))
        drawn = {"grid_points": int(np.isfinite(sig).sum())}
    else:
        ax.plot(res.points[:, 0], res.points[:, 1], color="0.6", lw=0.8, zorder=1)
        im = ax.scatter(res.points[:, 0], res.points[:, 1], c=sig, s=9, cmap=_CMAP, norm=norm,
                        zorder=2)
        drawn = {"path_points": int(np.isfinite(sig).sum())}
    g = lay.gcp_xyz + lay.origin
    if g.shape[0]:
        ax.scatter(g[:, 0], g[:, 1], marker="s", s=22, facecolor="white", edgecolor="k",
                   label="markers (GCP)", zorder=3)
        hull = horizontal_hull(g[:, :2])
        if hull is not None:
            ax.add_patch(Polygon(hull, closed=True, fill=False, ls=":", lw=1.0, ec="k",
                                 label="markers' convex hull"))
    xyz = lay.station_xyz()
    tracking = set(lay.stations)
    for s, p in xyz.items():
        ax.scatter([p[0]], [p[1]], marker="^", s=70, color="#D55E00" if s in tracking else "0.4",
                   edgecolor="k", zorder=4)
        ax.annotate(s, (p[0], p[1]), xytext=(5, 5), textcoords="offset points", fontsize=9)
        if s in tracking:
            ax.add_patch(Circle((p[0], p[1]), RANGE_LIMIT_M, fill=False, ls="--", lw=0.8,
                                ec="#D55E00", alpha=0.8))
    drawn["stations"] = len(xyz)
    drawn["markers"] = int(g.shape[0])
    drawn["range_circles"] = len(tracking)
    s = res.summary()["sigma_mm"]
    title = res.name if s["median"] is None else \
        f"{res.name}: median {s['median']:.2f} mm, 90 % {s['p90']:.2f} mm"
    ax.set_title(title, fontsize=10)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3, alpha=0.5)
    return im, drawn


def draw_plan_map(results: Sequence[PlanResult]) -> DrawnFigure:
    """The map of one plan, or of two side by side with one colour scale (module
    docstring)."""
    n = len(results)
    fig = Figure(figsize=(6.4 * n + 1.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, n, squeeze=False)[0]
    norm = _norm(results)
    points: dict[str, int] = {}
    im = None
    for k, (ax, res) in enumerate(zip(axes, results, strict=True)):
        im, drawn = _panel(ax, res, norm)
        points.update({f"{key} {k + 1}": v for key, v in drawn.items()})
    area = results[0].kind == "area"
    label = "pose sigma sqrt(tr Σ_t) (mm)" + (
        f", median over {results[0].headings_deg.size} headings" if area else "")
    fig.colorbar(im, ax=list(axes), label=label, shrink=0.85)
    axes[0].legend(loc="best", fontsize=8)
    caption = ("Predicted pose sigma (linear engine) "
               + ("over the area, the median over the robot's headings" if area
                  else "along the path") + f"; stations (triangles) with their "
               f"{RANGE_LIMIT_M:g} m circles (the paper's advice), markers (squares) and "
               "their convex hull" + ("; both plans on one colour scale." if n > 1 else "."))
    return DrawnFigure("plan_map", fig, points=points, caption=caption)


def _advice_rows(advice: dict) -> str:
    rows = []
    r, h, m = advice["ranges"], advice["gcp_hull"], advice["gcp_markers"]
    rows.append(("ranges", r["advice"], f"{100 * r['fraction_beyond']:.0f} % of the points "
                 f"beyond {r['limit_m']:g} m (largest {r['max_m']:.0f} m)", r["verdict"]))
    rows.append(("markers around the area", h["advice"],
                 f"{100 * h['fraction_outside']:.0f} % of the points outside "
                 f"({h['markers']} markers)", h["verdict"]))
    rows.append(("markers per station", m["advice"],
                 ", ".join(f"station {s}: {k}" for s, k in m["per_station"].items()),
                 m["verdict"]))
    return "".join(f"<tr><td class='s'>{html.escape(a)}</td><td class='s'>{html.escape(b)}"
                   f"</td><td class='s'>{html.escape(c)}</td><td class='s'>{html.escape(d)}"
                   "</td></tr>" for a, b, c, d in rows)


def _mm(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def plan_section_html(results: Sequence[PlanResult], figure: DrawnFigure,
                      figure_format: str = "svg") -> str:
    """The plan's section: per plan its key numbers and the advice, then the map."""
    parts = ["<section id='plan'><h2>Predicted ground-truth uncertainty</h2>"]
    for res in results:
        s = res.summary()
        mo = res.motion.to_dict()
        q = mo["qc_moving_m2_s3"]
        parts.append(
            f"<h3>{html.escape(res.name)}</h3><p>Layout: {html.escape(res.layout.source)}; "
            f"{len(res.layout.stations)} tracking stations, {res.layout.gcp_xyz.shape[0]} "
            f"markers; {s['points_predicted']} of {s['points']} points predicted "
            f"({html.escape(s['statistic'])}). Robot: {mo['speed_m_s']:g} m/s, GP Qc "
            f"{q['horizontal']:.2g} (horizontal), {q['vertical']:.2g} (vertical) m²/s³ "
            f"({html.escape(mo['qc_source'])}).</p>"
            "<table><tr><th class='k'>pose sigma</th><th>median</th><th>90 %</th>"
            "<th>largest</th></tr>"
            + "".join(f"<tr><td class='k'>{k}</td><td>{_mm(s[key]['median'])}</td>"
                      f"<td>{_mm(s[key]['p90'])}</td><td>{_mm(s[key]['max'])}</td></tr>"
                      for k, key in (("translation (mm)", "sigma_mm"),
                                     ("translation, worst heading (mm)", "sigma_worst_mm"),
                                     ("rotation (mrad)", "rotation_sigma_mrad")))
            + "</table><table><tr><th class='k'>advice</th><th class='k'>what</th>"
              "<th class='k'>this plan</th><th class='k'>verdict</th></tr>"
            + _advice_rows(s["advice"]) + "</table>")
    parts.append(figure_html(figure, figure_format))
    parts.append("<p><small>Method: docs/planning.md (the run's stages with the linear "
                 "engines, the GP on a stationary track).</small></p></section>")
    return "".join(parts)


def render_plan_page(results: Sequence[PlanResult], figure: DrawnFigure) -> str:
    """A self-contained HTML page of :func:`plan_section_html`."""
    title = "rtsgt plan: " + " vs ".join(r.name for r in results)
    return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body><main>"
            f"<h1>{html.escape(title)}</h1><p>rtsgt {html.escape(__version__)}</p>"
            f"{plan_section_html(results, figure)}</main></body></html>\n")

