"""A single self-contained HTML report of one run: tables, figures and an interactive 3D view.

Opens offline: the figures are embedded as data URIs and plotly.js inline (the optional
``rtsgt[report]`` extra; without plotly a note replaces the 3D view). Sections: key numbers,
the self-checks, the per-source tables, the figures of :mod:`rtsgt.report.figures`, the 3D
view (95 % position ellipsoids of a subsample, magnified) and what ``summary.json`` holds
that a reader needs. Prints on A4 without the 3D view.
"""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import math
import os
import urllib.parse
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from os import PathLike
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg

from rtsgt import __version__
from rtsgt.calibration.result import CALIBRATION_MODEL_NAMES, CALIBRATION_WEIGHTING_NAMES
from rtsgt.checks.verdict import record_verdict
from rtsgt.errors import RtsgtWarning
from rtsgt.io._parse import atomic_write_text
from rtsgt.io.run_dir import read_run
from rtsgt.record import RunRecord
from rtsgt.report.analysis import DEFAULT_BINS_M, PAPER_CITATION, Analysis, analyze
from rtsgt.report.figures import (
    SOURCE_LABELS,
    DrawnFigure,
    body_origin_offset,
    break_gaps,
    draw_all,
    nice_scale,
    rejected_positions,
)
from rtsgt.report.style import CSS

__all__ = [
    "CHI2_3_95",
    "VIEW3D_ID",
    "ReportInfo",
    "ellipsoid_mesh",
    "render_report",
    "scene_box",
    "view3d_figure",
    "write_report",
    "write_report_file",
]

#: chi-square(3) 0.95 quantile: the 95 % ellipsoid of a 3-D Gaussian.
CHI2_3_95 = 7.814727903251178
#: id of the 3D view's element in the page.
VIEW3D_ID = "rtsgt-view3d"
#: The 3D view's margin about everything it draws, as a fraction of the largest extent.
SCENE_MARGIN = 0.05
#: The 3D view's least height, as a fraction of the largest extent.
SCENE_MIN_HEIGHT = 0.15
#: Where the 3D view's camera stands, in plotly's scene units (the box's longest side is 1).
CAMERA_EYE = (1.0, 1.0, 0.8)



@dataclass(frozen=True)
class ReportInfo:
    """What :func:`write_report_file` wrote: the HTML ``path`` and its ``size_bytes``, the names of
    the embedded ``figures``, whether the 3D view is in (``view3d``: plotly available), its
    ``n_ellipsoids`` and their magnification ``ellipsoid_scale`` (or None)."""

    path: Path
    size_bytes: int
    figures: tuple[str, ...]
    view3d: bool
    n_ellipsoids: int
    ellipsoid_scale: float | None


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            return "–"
        return f"{v:.{digits}g}"
    return html.escape(str(v))


def _sources_table(a: Analysis) -> str:
    head = ["<tr><th class='k' rowspan='2'>source</th><th colspan='2'>all ranges</th>"]
    head += [f"<th colspan='2'>{html.escape(lab)}<br><small>n = {c} "
             f"({100 * sh:.0f} %)</small></th>"
             for lab, c, sh in zip(a.bin_labels, a.bin_counts, a.bin_shares, strict=True)]
    head.append("</tr><tr>" + "<th>this run</th><th class='paper'>paper</th>"
                * (len(a.bin_labels) + 1) + "</tr>")
    rows = []
    for r in a.table_rows():
        cls = " class='all'" if r["source"] == "all" else ""
        cells = [f"<td class='s'>{html.escape(SOURCE_LABELS.get(r['source'], r['source']))}</td>",
                 f"<td>{_fmt(r['median_mm'], 3)}</td>",
                 f"<td class='paper'>{_fmt(r['paper_median_mm'], 3)}</td>"]
        for b in r["bins"]:
            cells.append(f"<td>{_fmt(b['median_mm'], 3)}</td>"
                         f"<td class='paper'>{_fmt(b['paper_median_mm'], 3)}</td>")
        rows.append(f"<tr{cls}>{''.join(cells)}</tr>")
    return ("<table id='sources-table'>" + "".join(head) + "".join(rows) + "</table>"
            f"<p><small>Median of sqrt(||Σ||<sub>F</sub>) of each source's 3x3 prism "
            f"covariance, mm, over {a.n_measurements} measurements. Paper: "
            f"{html.escape(PAPER_CITATION)}.</small></p>")


_ALL_CLASS = " class='all'"


def _pose_table(a: Analysis) -> str:
    rows = "".join(
        f"<tr{_ALL_CLASS if r['source'] == 'all' else ''}>"
        f"<td class='s'>{html.escape(SOURCE_LABELS.get(r['source'], r['source']))}</td>"
        f"<td>{_fmt(r['translation_mm'], 3)}</td><td>{_fmt(r['rotation_mrad'], 3)}</td></tr>"
        for r in a.pose_rows())
    measure = "sqrt(trace)" if a.pose_measure == "sqrt_trace" else "sqrt(largest eigenvalue)"
    return ("<table id='pose-table'><tr><th class='k'>source</th><th>translation (mm)</th>"
            f"<th>rotation (mrad)</th></tr>{rows}</table><p><small>Medians over "
            f"{a.pose_t.size} kept poses, {a.engine} engine, {measure} of each 3x3 block of "
            "the 6x6 pose covariance.</small></p>")


def _interval(v: Mapping) -> str:
    iv = v.get("interval_95")
    return "-" if not iv else f"{_fmt(iv[0], 3)} - {_fmt(iv[1], 3)}"


def _self_checks_html(checks: Mapping) -> str:
    """The run's self-checks (:mod:`rtsgt.checks`): the inter-prism distances by regime, the
    block cross-validation of the tracks by regime and the GCP fit per station, each with its
    95 % interval and verdict, and the noise on the static stretches."""
    if not checks:
        return "<p class='note'>This run was written before rtsgt made self-checks.</p>"
    parts = []
    d = checks.get("inter_prism_distances", {})
    rows = [("whole run", d.get("overall")), *d.get("regimes", {}).items()]
    body = "".join(
        f"<tr><td class='s'>{html.escape(k)}</td><td>{v['poses']}</td>"
        f"<td>{_fmt(v['mean_z2'], 3)}</td><td>{_fmt(v.get('n_eff'), 3)}</td>"
        f"<td>{_interval(v)}</td><td class='verdict'>{html.escape(v['verdict'])}</td></tr>"
        for k, v in rows if v)
    parts.append(
        "<h3>Inter-prism distances</h3><table id='check-distances'><tr><th class='k'>regime"
        "</th><th>poses</th><th>mean z²</th><th>n_eff</th><th>95 % interval</th>"
        f"<th>verdict</th></tr>{body}</table><p><small>z = (tracked − surveyed inter-prism "
        "distance) / its predicted sigma; the mean of z² is 1 if the covariance is honest, "
        "below it pessimistic, above optimistic. n_eff counts the errors shared by the run. "
        "Method: rtsgt's docs/self-checks.md.</small></p>")
    cv = checks.get("block_cv", {})
    if cv:
        rows = [("whole run", cv.get("overall")), *cv.get("regimes", {}).items()]
        body = "".join(
            f"<tr><td class='s'>{html.escape(k)}</td><td>{v['blocks']}</td>"
            f"<td>{v['measurements']}</td><td>{_fmt(v['nees_per_dof'], 3)}</td>"
            f"<td>{_fmt(v.get('n_eff'), 3)}</td><td>{_interval(v)}</td>"
            f"<td class='verdict'>{html.escape(v['verdict'])}</td></tr>"
            for k, v in rows if v)
        lengths = " and ".join(f"{x:g} s" for x in cv.get("block_lengths_s", []))
        parts.append(
            "<h3>Block cross-validation of the tracks</h3><table id='check-block-cv'><tr>"
            "<th class='k'>regime</th><th>windows</th><th>measurements</th><th>NEES / dof</th>"
            f"<th>n_eff</th><th>95 % interval</th><th>verdict</th></tr>{body}</table><p><small>"
            f"Windows of {lengths} of each prism track held out in turn and predicted by its GP "
            "refitted on the rest with the run's Qc; the prediction error against the GP's "
            "covariance plus the white measurement covariance (1 if honest, below it "
            "pessimistic, above optimistic). Regimes: the robot's motion across the window "
            "(standing, steady, accelerating from 0.1 m/s²) and its centre's distance to the "
            "nearest kept measurement (near: under 1 s). Method: rtsgt's docs/self-checks.md."
            "</small></p>")
    g = checks.get("gcp_fit", {})
    body = "".join(
        f"<tr><td class='s'>station {html.escape(str(s))}</td><td>{v['markers']}</td>"
        f"<td>{_fmt(v['variance_factor'], 3)}</td>"
        + "".join(f"<td>{_fmt(x, 3)}</td>" for x in v["axis_factors_xyz"])
        + f"<td>{_interval(v)}</td><td class='verdict'>{html.escape(v['verdict'])}</td></tr>"
        for s, v in g.get("stations", {}).items())
    added = g.get("added_shot_sigma_mm", {})
    parts.append(
        "<h3>GCP fit</h3><table id='check-gcp'><tr><th class='k'>station</th><th>markers</th>"
        "<th>variance factor</th><th>x</th><th>y</th><th>z</th><th>95 % interval</th>"
        f"<th>verdict</th></tr>{body}</table><p><small>The residuals of each station's fit "
        f"({html.escape(CALIBRATION_MODEL_NAMES.get(g.get('model'), 'model unknown'))}; "
        f"{html.escape(CALIBRATION_WEIGHTING_NAMES.get(g.get('weighting'), 'weights unknown'))}) "
        "against the instrument model's covariance (1 if the model is right). Added to every "
        f"shot by the calibration: {_fmt(added.get('horizontal'), 3)} mm horizontal, "
        f"{_fmt(added.get('vertical'), 3)} mm vertical.</small></p>")
    parts.append(_levelling_html(g.get("levelling")))
    parts.append(_dynamic_calibration_html(checks.get("dynamic_calibration")))
    parts.append(_static_noise_html(checks.get("static_noise")))
    parts.append(_static_relative_html(checks.get("static_relative")))
    parts.append(_raw_block_cv_html(checks.get("raw_block_cv")))
    parts.append(_structure_html(checks.get("inter_prism_structure")))
    return "".join(parts)


def _levelling_html(lev: Mapping | None) -> str:
    """The levelling test of the GCP fit: per station the tilt a free rotation fits beyond the
    Earth's curvature (x, y, µrad) with its sigma, chi-square, p and verdict."""
    if not lev:
        return ""
    body = "".join(
        f"<tr><td class='s'>station {html.escape(str(s))}</td>"
        + "".join(f"<td>{_fmt(t, 3)} ± {_fmt(e, 2)}</td>"
                  for t, e in zip(v["tilt_urad"], v["sigma_urad"], strict=True))
        + f"<td>{_fmt(v['chi2'], 3)}</td><td>{_fmt(v['p_value'], 2)}</td>"
        f"<td class='verdict'>{html.escape(str(v.get('verdict')))}</td></tr>"
        for s, v in lev.items() if isinstance(v, Mapping) and "tilt_urad" in v)
    return ("<table id='check-levelling'><tr><th class='k'>levelling</th><th>tilt x (µrad)</th>"
            "<th>tilt y (µrad)</th><th>χ² (2 dof)</th><th>p</th><th>verdict</th></tr>"
            f"{body}</table><p><small>The tilt of each station that a free rotation fits beyond "
            "the Earth's curvature, against its uncertainty (levelled when it is within it). "
            "Method: rtsgt's docs/noise-model.md.</small></p>")


def _dynamic_calibration_html(check: Mapping | None) -> str:
    """The dynamic (or joint) calibration's self-check
    (:func:`rtsgt.checks.calibration.dynamic_calibration_check`): the clock offsets, the
    variance factor of the inter-prism distances and the agreement with the GCPs."""
    if not check:
        return ""
    clocks = "".join(
        f"<tr><td class='s'>station {html.escape(str(s))}</td><td>{_fmt(v, 3)} ± "
        f"{_fmt(check['clock_sigma_ms'][s], 2)}</td></tr>"
        for s, v in check.get("clock_offset_ms", {}).items())
    out = [
        f"<h3>{html.escape(check['method'].capitalize())} calibration</h3>"
        "<table id='check-dynamic-calibration'><tr><th class='k'>samples</th>"
        "<th>variance factor</th><th>effective dof</th><th>95 % interval</th><th>verdict</th>"
        f"</tr><tr><td class='s'>{check['samples']}</td>"
        f"<td>{_fmt(check['variance_factor'], 3)}</td><td>{_fmt(check['dof'], 3)}</td>"
        f"<td>{_interval(check)}</td><td class='verdict'>{html.escape(check['verdict'])}</td>"
        "</tr></table>"
        "<table id='check-dynamic-clocks'><tr><th class='k'>clock offset (ms)</th><th>against "
        f"the reference station</th></tr>{clocks}</table>"]
    agree = check.get("gcp_agreement")
    if agree:
        body = "".join(
            f"<tr><td class='s'>station {html.escape(str(s))}</td><td>{_fmt(v['chi2'], 3)}</td>"
            f"<td>{v['dof']}</td><td>{_fmt(v['p_value'], 2)}</td>"
            f"<td>{_fmt(max(abs(z) for z in v['z'].values()), 3)}</td>"
            f"<td class='verdict'>{html.escape(v['verdict'])}</td></tr>"
            for s, v in agree.items())
        out.append(
            "<table id='check-dynamic-gcp'><tr><th class='k'>against the GCPs</th><th>χ²</th>"
            "<th>dof</th><th>p</th><th>largest |z|</th><th>verdict</th></tr>"
            f"{body}</table>")
    out.append(
        "<p><small>The stations fitted to the robot's motion through the surveyed inter-prism "
        "distances (with the GCPs for a joint calibration). The variance factor compares the "
        "distance residuals with the tracks' covariance and the shared errors (1 if honest); "
        "the clock offsets are those of each station relative to the reference station's "
        "(reported, not applied); a dynamic calibration is compared with the GCP calibration "
        "of the same deployment in units of their combined covariance. Method: rtsgt's "
        "docs/calibration.md.</small></p>")
    return "".join(out)


def _structure_html(check: Mapping | None) -> str:
    """The inter-prism residual structure check (:mod:`rtsgt.checks.structure`): its two
    tests, the clock offsets (whole run and per window) and the prisms' harmonic
    amplitudes."""
    if not check or "clock" not in check:
        return ""
    ck, po = check["clock"], check["prism_orientation"]
    rows = [("clock offsets", "χ² / dof", ck.get("chi2_per_dof"), ck),
            ("prism orientation", "F", po.get("f"), po)]
    body = "".join(
        f"<tr><td class='s'>{k}</td><td>{stat}</td><td>{_fmt(x, 3)}</td>"
        f"<td>{_fmt(v.get('critical'), 3)}</td><td>{_fmt(v.get('p_value'), 2)}</td>"
        f"<td>{_fmt(v.get('dof'))}</td>"
        f"<td class='verdict'>{html.escape(str(v.get('verdict') or '–'))}</td></tr>"
        for k, stat, x, v in rows)
    out = [
        "<h3>Inter-prism residual structure</h3><table id='check-structure'><tr>"
        "<th class='k'>test</th><th>statistic</th><th>value</th>"
        f"<th>critical ({100 * ck.get('level', 0.975):.1f} %)</th><th>p</th><th>dof</th>"
        f"<th>verdict</th></tr>{body}</table>"]
    clock = check["clock"]
    if clock.get("offsets_ms"):
        pairs = list(clock["offsets_ms"])
        head = "".join(f"<th>{html.escape(p)}</th>" for p in pairs)
        run = "".join(f"<td>{_fmt(v['run'], 3)} ± {_fmt(v['sigma'], 2)}</td>"
                      for v in clock["offsets_ms"].values())
        bw = clock.get("by_window", {})
        starts = bw.get("t_start", [])
        win = "".join(
            f"<tr><td class='s'>from {_fmt(t0 - starts[0], 4)} s</td>"
            + "".join(f"<td>{_fmt(bw['offsets_ms'][p][w], 3)} ± "
                      f"{_fmt(bw['sigma_ms'][p][w], 2)}</td>" for p in pairs) + "</tr>"
            for w, t0 in enumerate(starts))
        out.append(
            "<table id='check-clock-offsets'><tr><th class='k'>clock offsets, ms</th>"
            f"{head}</tr><tr><td class='s'>whole run</td>{run}</tr>{win}</table>")
    amp = check["prism_orientation"].get("amplitudes", {})
    if amp:
        body = "".join(
            f"<tr><td class='s'>prism {html.escape(str(p))}, {html.escape(k)}</td>"
            f"<td>{_fmt(a['range_mm'], 3)} ± {_fmt(a['range_sigma_mm'], 2)}</td>"
            f"<td>{_fmt(a['across_mm'], 3)} ± {_fmt(a['across_sigma_mm'], 2)}</td></tr>"
            for p, per in amp.items() for k, a in per.items())
        out.append("<table id='check-prism-harmonics'><tr><th class='k'>harmonic (per turn)"
                   "</th><th>range, mm</th><th>across, mm</th></tr>" + body + "</table>")
    out.append(
        "<p><small>GLS regression of the inter-prism distance residuals, with the run's own "
        "covariance (the GP's and the errors shared by the run), on the clock offsets of the "
        "stations relative to the first per window of "
        f"{_fmt(check.get('window_s'), 3)} s of motion (χ² / dof is 1 if the covariance is "
        "honest), and on the 6 and 12 per turn harmonics of each prism's viewing angle "
        "against harmonics no six-cube prism has (F is 1 without a prism error). One-sided, "
        "each at half the family's 5 %. Method: rtsgt's docs/self-checks.md.</small></p>")
    return "".join(out)


def _tau(co: Mapping) -> str:
    """A correlation time with its 95 % interval, or a dash."""
    tau, iv = co.get("correlation_time_s"), co.get("correlation_time_95_s")
    if tau is None:
        return "–"
    if not iv:
        return _fmt(tau, 2)
    return f"{_fmt(tau, 2)} ({_fmt(iv[0], 2)} – " + ("…)" if iv[1] is None
                                                     else f"{_fmt(iv[1], 2)})")


def _raw_block_cv_html(c: Mapping | None) -> str:
    """The joint engine's block cross-validation of the raw measurements, overall and per
    station (docs/joint.md)."""
    if not c:
        return ""
    rows = [("whole run", c.get("overall")),
            *((f"station {k}", v) for k, v in (c.get("stations") or {}).items())]
    body = "".join(
        f"<tr><td class='s'>{html.escape(k)}</td><td>{v['blocks']}</td>"
        f"<td>{v['measurements']}</td><td>{_fmt(v['nees_per_dof'], 3)}</td>"
        f"<td>{_fmt(v.get('n_eff'), 3)}</td><td>{_interval(v)}</td>"
        f"<td class='verdict'>{html.escape(v['verdict'])}</td></tr>" for k, v in rows if v)
    return ("<h3>Block cross-validation of the raw measurements</h3><table "
            "id='check-raw-block-cv'><tr><th class='k'></th><th>blocks</th><th>measurements"
            "</th><th>NEES / dof</th><th>n_eff</th><th>95 % interval</th><th>verdict</th></tr>"
            f"{body}</table><p><small>Blocks of 1 s and 2 s of each station's measurements "
            "(Hz, V, d), each predicted from the other stations and the prior by the joint "
            "solution without it; 1 if the measurements' covariance and the motion prior are "
            "honest. Method: rtsgt's docs/joint.md.</small></p>")


def _static_relative_html(c: Mapping | None) -> str:
    """The relative poses on the static stretches per lag (docs/self-checks.md)."""
    if not c or "lags" not in c:
        return "" if not c else f"<p class='note'>{html.escape(c.get('note', ''))}</p>"
    body = "".join(
        f"<tr><td class='s'>{html.escape(k)} s</td><td>{v['pairs']}</td>"
        f"<td>{_fmt(v['nees_per_dof'], 3)}</td><td>{_fmt(v['position_nees_per_dof'], 3)}</td>"
        f"<td>{_fmt(v['rotation_nees_per_dof'], 3)}</td><td>{_fmt(v.get('n_eff'), 3)}</td>"
        f"<td>{_interval(v)}</td><td class='verdict'>{html.escape(v['verdict'])}</td></tr>"
        for k, v in c["lags"].items())
    return ("<h3>Relative poses on the static stretches</h3><table id='check-static-relative'>"
            "<tr><th class='k'>lag</th><th>pairs</th><th>NEES / dof</th><th>position</th>"
            "<th>rotation</th><th>n_eff</th><th>95 % interval</th><th>verdict</th></tr>"
            f"{body}</table><p><small>Where the robot stands, the ground truth's relative pose "
            "between two times is all error; its NEES against the run's covariance of the "
            f"difference is 1 if honest at that time scale ({c['stretches']} stretches, "
            f"{_fmt(c['static_s'], 3)} s). Method: rtsgt's docs/self-checks.md.</small></p>")


def _static_noise_html(s: Mapping | None) -> str:
    """The static-stretch noise check: per prism and component, the scatter against the
    predicted white sigma, its variance ratio and lag-one correlation with their intervals and
    verdicts, and the correlation time where correlation is found."""
    if s is None:
        return ""
    head = "<h3>Noise on the static stretches</h3>"
    if not s.get("prisms"):
        return head + f"<p>{html.escape(s.get('note', 'no static stretch'))}.</p>"

    def iv(v: Mapping) -> str:
        i = v.get("interval")
        return "" if not i else f"<br><small>{_fmt(i[0], 3)} – {_fmt(i[1], 3)}</small>"

    rows = []
    for pid, e in s["prisms"].items():
        rows.append(
            f"<tr class='group'><th class='k' colspan='7'>prism {html.escape(str(pid))} "
            f"<small>(station {html.escape(str(e['station']))}, {e['samples']} samples)"
            "</small></th></tr>")
        for name in ("range", "horizontal", "vertical"):
            c = e[name]
            lv, co = c["level"], c["correlation"]
            rows.append(
                f"<tr><td class='s'>{name}</td>"
                f"<td>{_fmt(c['observed_sigma_mm'], 3)} / {_fmt(c['predicted_sigma_mm'], 3)}</td>"
                f"<td>{_fmt(lv['variance_ratio'], 3)}{iv(lv)}</td>"
                f"<td class='verdict'>{html.escape(lv['verdict'])}</td>"
                f"<td>{_fmt(co['lag1'], 2)}{iv(co)}</td>"
                f"<td class='verdict'>{html.escape(co['verdict'])}</td>"
                f"<td>{_tau(co)}</td></tr>")
    spans = ", ".join(f"{b - a:.1f}" for a, b in s["stretches_s"])
    conf = s.get("confidence")
    within = "its interval" if not conf else f"its {100 * conf:.2f} % interval"
    level = "" if not conf else (
        f" Each interval holds {100 * conf:.2f} % ({s['tests']} tests: a run whose noise "
        f"model is right is flagged {100 * s['family_false_alarm']:.0f} % of the time).")
    return (head + "<table id='check-static'><tr><th class='k'>component</th>"
            "<th>scatter / predicted (mm)</th>"
            f"<th>variance ratio<br><small>{within}</small></th><th>verdict</th>"
            f"<th>lag-1 correlation<br><small>{within}</small></th><th>verdict</th>"
            f"<th>correlation time (s)<br><small>95 % interval</small></th></tr>{''.join(rows)}"
            f"</table><p><small>Static stretches of {spans} s. The scatter of each prism's "
            "measurements about their mean while the robot stands, along the line of sight "
            "(range) and across it, against the white noise the run predicts (instrument and "
            "tilt); a variance ratio above its interval: the model's noise is too small "
            "(optimistic), below: too large (pessimistic). A lag-one correlation above its "
            "interval: the noise wanders, and the GP averages errors that do not average out "
            f"(optimistic).{level} Method: rtsgt's docs/self-checks.md.</small></p>")


def _correlated_noise_html(plan: Mapping | None) -> str:
    """How the GPs carried the time-correlated noise the static-stretch check found
    (:mod:`rtsgt.noise.correlated`): per prism and component the correlated share, the
    correlation time, rho, the variance factor and whether it was applied."""
    if not plan or not plan.get("prisms"):
        return ""
    rows = []
    for pid, e in plan["prisms"].items():
        for name in ("range", "horizontal", "vertical"):
            c = e[name]
            rows.append(
                f"<tr><td class='s'>{html.escape(str(pid))}</td><td class='s'>{name}</td>"
                f"<td class='verdict'>{html.escape(str(c.get('verdict')))}</td>"
                f"<td>{_fmt(c.get('correlated_fraction'), 3)}</td>"
                f"<td>{_fmt(c.get('correlation_time_s'), 3)}</td>"
                f"<td>{_fmt(e.get('median_interval_s'), 3)}</td><td>{_fmt(c.get('rho'), 3)}</td>"
                f"<td>{_fmt(c.get('factor'), 3)}</td>"
                f"<td>{'yes' if c.get('applied') else 'no'}</td></tr>")
    mode = ("inflated where correlation was found" if plan.get("mode") == "inflate" else
            "not inflated (<code>correlated_noise = \"ignore\"</code>, the paper)")
    return ("<h3>Time-correlated noise carried</h3><table id='correlated-noise'><tr>"
            "<th class='k'>prism</th><th>component</th><th>correlation</th><th>f</th>"
            "<th>τ (s)</th><th>dt (s)</th><th>ρ</th><th>factor k</th><th>applied</th></tr>"
            f"{''.join(rows)}</table><p><small>White covariance {mode}: where the static "
            "stretches find the noise of a component correlated (f: its correlated share, τ: "
            "its correlation time, dt: the prism's median measurement interval), the white "
            "variance the GP is given along it is multiplied by k = (1 − f) + f (1 + ρ) / "
            "(1 − ρ), ρ = exp(−dt / τ): n correlated measurements average like n / k "
            "independent ones. Exact for a long average, conservative for a short one; the "
            "noise level stays the model's. Method: rtsgt's docs/noise-model.md."
            "</small></p>")


#: Readable names (with units) of the options of ``summary.json`` ``parameters``; an option
#: not listed here is shown under its key.
_OPTION_LABELS = {
    "engine": "pose engine",
    "registration": "registration of the reference prisms",
    "samples": "Monte Carlo samples",
    "seed": "random seed",
    "calibration_method": "calibration method",
    "calibration_model": "calibration model",
    "calibration_weighting": "calibration weighting",
    "rate_hz": "ground-truth rate (Hz)",
    "qc": "GP Qc",
    "max_gap_s": "longest gap bridged (s)",
    "gp_noise": "noise given to the GP",
    "motion_prior": "Qc along the motion",
    "outlier_windows": "windows of distance rejections",
    "prior": "GP motion prior",
    "correlated_noise": "time-correlated noise",
    "noise_sources": "noise sources",
    "instrument": "instrument",
    "filter": "filter thresholds",
    "distance_gate_m": "distance gate (m)",
    "uncertainty_gate_m": "uncertainty gate (m)",
}
#: Units of the filter thresholds (``parameters.filter``; rtsgt.filtering.modules).
_FILTER_UNITS = {"tau_r": "m/s", "tau_a": "rad/s", "tau_e": "rad/s", "tau_s": "s",
                 "tau_l": "s"}


def _plain(v) -> str:
    """A value of summary.json as short text: numbers to 4 significant digits, lists joined,
    mappings as ``key value`` pairs."""
    if isinstance(v, Mapping):
        return ", ".join(f"{html.escape(str(k))} {_plain(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return ", ".join(_plain(x) for x in v)
    return _fmt(v)


def _vec(v, spec: str = ".3g") -> str:
    """A short vector as ``a, b, c``, each number formatted by ``spec``."""
    return "–" if not v else ", ".join(format(float(x), spec) for x in v)


def _kv_table(table_id: str, rows: Sequence[tuple[str, str]]) -> str:
    """A two-column table of (name, value) rows (both already HTML)."""
    if not rows:
        return ""
    body = "".join(f"<tr><th class='k'>{k}</th><td class='s'>{v}</td></tr>" for k, v in rows)
    return f"<table id='{table_id}' class='kv'>{body}</table>"


def _utc(t) -> str:
    if not isinstance(t, (int, float)) or not math.isfinite(t):
        return "–"
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def _run_info_html(summary: Mapping) -> str:
    rows = []
    if "deployment" in summary:
        rows.append(("deployment", _fmt(summary["deployment"])))
    cfg = (summary.get("inputs") or {}).get("config")
    if cfg:
        rows.append(("configuration", f"<code>{html.escape(str(cfg))}</code>"))
    sw = summary.get("software") or {}
    if sw:
        schema = (summary.get("schema") or {}).get("version")
        rows.append(("written by", f"{_fmt(sw.get('name'))} {_fmt(sw.get('version'))}"
                     + ("" if schema is None else f" (summary layout {_fmt(schema)})")))
    poses = summary.get("poses") or {}
    if poses:
        rows.append(("ground truth", f"{_utc(poses.get('first_t'))} to "
                                     f"{_utc(poses.get('last_t'))}"))
        rej = poses.get("rejected_by_reason") or {}
        rows.append(("poses", f"{_fmt(poses.get('kept'))} kept of {_fmt(poses.get('queried'))}"
                     + ("; rejected: " + _plain(rej) if rej else "")))
    med = summary.get("median_uncertainty") or {}
    if med:
        rows.append(("median pose sigma", f"{_fmt(med.get('translation_mm'), 3)} mm, "
                                          f"{_fmt(med.get('rotation_mrad'), 3)} mrad"))
    iv = summary.get("intervals_s") or []
    if iv:
        rows.append(("common intervals (module 2)", f"{len(iv)}, lasting "
                     + ", ".join(f"{b - a:.1f}" for a, b in iv) + " s"))
    w = summary.get("weather")
    if isinstance(w, Mapping) and w:
        rows.append(("weather", f"<code>{html.escape(str(w.get('file')))}</code>, a record every "
                     f"{_fmt(w.get('sampling_interval_s'), 6)} s; covers every measurement: "
                     f"{_fmt(w.get('covered'))}"))
    elif "weather" in summary:
        rows.append(("weather", "none (standard atmosphere)"))
    return _kv_table("run-info", rows)


def _options_html(params: Mapping) -> str:
    rows = []
    for k, v in params.items():
        if k == "filter" and isinstance(v, Mapping):
            shown = ", ".join(f"{html.escape(str(n))} {_fmt(x)} {_FILTER_UNITS.get(n, '')}".strip()
                              for n, x in v.items())
        else:
            shown = _plain(v)
        rows.append((html.escape(_OPTION_LABELS.get(k, k)) + f" <small>({html.escape(k)})</small>",
                     shown))
    return _kv_table("run-options", rows)


def _filters_html(filters: Mapping) -> str:
    rows = []
    for name, f in filters.items():
        if not isinstance(f, Mapping) or "n_in" not in f:
            continue
        removed = {k: v for k, v in (f.get("removed") or {}).items() if v}
        label = name.replace("_station", ", station ").replace("module", "module ")
        rows.append(f"<tr><td class='s'>{html.escape(label)}</td><td>{_fmt(f['n_in'])}</td>"
                    f"<td>{_fmt(f.get('n_kept'))}</td>"
                    f"<td class='s'>{_plain(removed) if removed else '–'}</td></tr>")
    if not rows:
        return ""
    return ("<table id='run-filters'><tr><th class='k'>filter</th><th>in</th><th>kept</th>"
            f"<th>removed, by reason</th></tr>{''.join(rows)}</table>")


def _prisms_html(prisms: Mapping) -> str:
    rows = []
    for pid, p in prisms.items():
        if not isinstance(p, Mapping):
            continue
        qc = p.get("qc_m2_s3")
        diag = "–" if not qc else ", ".join(_fmt(qc[i][i], 3) for i in range(len(qc)))
        prior = str(p.get("prior", "wnoa"))
        fit = p.get("qc_fit") or {}
        rows.append(f"<tr><td class='s'>{html.escape(str(pid))}</td>"
                    f"<td class='s'>{_fmt(p.get('station'))}</td>"
                    f"<td>{_fmt(p.get('measurements_used'))}</td>"
                    f"<td class='s'>{html.escape(prior.upper())}</td>"
                    f"<td class='s'>{diag}</td><td class='s'>{_fmt(fit.get('method'))}</td>"
                    f"<td>{_fmt(fit.get('loo_nees_per_dof'), 3)}</td>"
                    f"<td>{_fmt(p.get('median_sigma_mm'), 3)}</td></tr>")
    if not rows:
        return ""
    return ("<table id='run-prisms'><tr><th class='k'>prism</th><th>station</th>"
            "<th>measurements</th><th>prior</th><th>Qc x, y, z<br><small>m²/s³ (WNOJ: m²/s⁵)"
            "</small></th><th>Qc fit</th>"
            "<th>leave-one-out NEES / dof</th><th>median sigma (mm)</th></tr>"
            f"{''.join(rows)}</table>")


def _calibration_html(cal: Mapping) -> str:
    if not cal:
        return ""
    rows = []
    for sid, st in (cal.get("stations") or {}).items():
        if not isinstance(st, Mapping):
            continue
        rows.append(f"<tr><td class='s'>{html.escape(str(sid))}</td>"
                    f"<td>{_fmt(st.get('yaw_deg'), 6)}</td>"
                    f"<td>{_vec(st.get('translation_m'), '.3f')}</td>"
                    f"<td>{_vec(st.get('sigma_translation_mm'))}</td>"
                    f"<td>{_vec(st.get('sigma_rotation_mrad'))}</td></tr>")
    res = cal.get("residuals_mm") or {}
    note = (f"<p><small>Method {_fmt(cal.get('method'))}, model {_fmt(cal.get('model'))}, "
            f"reference station {_fmt(cal.get('reference_station'))}"
            + (f"; GCP residuals: median {_fmt(res.get('median'), 3)} mm, largest "
               f"{_fmt(res.get('max'), 3)} mm over {_fmt(res.get('count'))}" if res else "")
            + ".</small></p>")
    if not rows:
        return note
    return ("<table id='run-calibration'><tr><th class='k'>station</th><th>yaw (deg)</th>"
            "<th>translation (m)</th><th>sigma translation (mm)</th>"
            f"<th>sigma rotation (mrad)</th></tr>{''.join(rows)}</table>{note}")


def _pm(v, sd, digits: int = 3) -> str:
    """``v ± sd`` (numbers or None)."""
    return f"{_fmt(v, digits)} ± {_fmt(sd, 2)}"


def _rows_table(table_id: str, headers: Sequence[str], rows: Sequence[str]) -> str:
    """A table of ``rows`` (``<tr>`` HTML) under ``headers`` (HTML, the first the key's);
    empty without rows."""
    if not rows:
        return ""
    head = "".join(f"<th class='k'>{h}</th>" if i == 0 else f"<th>{h}</th>"
                   for i, h in enumerate(headers))
    return f"<table id='{table_id}'><tr>{head}</tr>{''.join(rows)}</table>"


def _joint_noise_row(sid, ch: str, w: Mapping | None, g: Mapping | None) -> str:
    """One station's and channel's noise row: the white factor (and range part) where
    determined (alone, or pooled over the stations), else the prior's, the white sigma at
    the station's median range, and the Gauss-Markov chain's sigma and tau where
    determined."""
    det = (w or {}).get("determined") or [False, False]
    at = (w or {}).get("sigma_at_median")
    at_text = "" if at is None else (
        f"; σ {_pm(at, w.get('sigma_at_median_sigma')) if any(det) else _fmt(at, 3)} "
        f"{'mm' if ch == 'd' else 'mgon'} at {_fmt(w.get('median_range_m'), 3)} m")
    white = ("–" if not w else
             (_pm(w.get("factor"), w.get("factor_sigma"))
              + (" (pooled over the stations)" if w.get("pooled") else "") if det[0]
              else f"{_fmt(w.get('factor'), 3)} (the prior, kept)")
             + (f"; range part {_fmt(w.get('range_part'), 3)} "
                f"{'ppm' if ch == 'd' else 'mgon at 100 m'}" if det[1] else "")
             + at_text)
    corr = ("–" if not g else "not determined, not carried" if not g.get("determined")
            else f"{_pm(g.get('sigma'), g.get('sigma_sigma'))} {'mm' if ch == 'd' else 'mgon'}"
                 f", τ {_pm(g.get('tau_s'), g.get('tau_sigma_s'))} s")
    return (f"<tr><td class='s'>{html.escape(str(sid))}</td><td class='s'>{ch}</td>"
            f"<td class='s'>{white}</td><td class='s'>{corr}</td></tr>")


def _blind_text(prism: Mapping) -> str:
    """A prism's moves no station sees (``blind_directions``, ``blind_turn_mrad_per_mm`` of
    ``summary.json``'s ``joint.prisms``): each direction and the poses' turn per mm along
    it; none where the other prisms hold every direction (docs/joint.md#what-no-station-sees)."""
    dirs = prism.get("blind_directions") or []
    turns = prism.get("blind_turn_mrad_per_mm") or []
    if not dirs:
        return "none"
    return "; ".join(f"({_vec(d, '.2f')}): {_fmt(t, 3)} mrad per mm"
                     for d, t in zip(dirs, turns, strict=True))


def _loop_text(j: Mapping) -> str:
    """The variance components' loop of a joint run: its updates and whether it converged
    (docs/joint.md#the-variance-components-loop)."""
    if j.get("qc_converged") is None:  # (a summary written before the field)
        return f"{_fmt(j.get('qc_iterations'))} updates"
    if j.get("qc_converged"):
        return f"{_fmt(j.get('qc_iterations'))} updates, converged"
    parts = ", ".join(f"{html.escape(str(k))} {_fmt(100 * v, 3)} %"
                      for k, v in (j.get("qc_last_change") or {}).items())
    return (f"{_fmt(j.get('qc_iterations'))} updates, not converged (the last one's largest "
            f"changes: {parts}): the estimates are where the loop stopped")


def _joint_html(j: Mapping) -> str:
    """What the joint engine estimated besides the poses (``summary.json``'s ``joint``), each
    estimate with its sigma: the solve, the stations' shifts from their calibration, the
    clocks, the prisms against their survey, the noise's white and correlated components,
    the tripods' settling and the motion axes (docs/joint.md)."""
    if not j:
        return ""
    parts = [_kv_table("run-joint", [
        ("solve", f"{_fmt(j.get('iterations'))} iterations, "
                  f"{'converged' if j.get('converged') else 'not converged'}, "
                  f"χ² / row {_fmt(j.get('chi2_per_dof'), 3)}"),
        ("variance components", _loop_text(j)),
        ("knots, measurements, poses",
         f"{_fmt(j.get('knots'))}, {_fmt(j.get('measurements'))}, {_fmt(j.get('poses'))}"),
        ("atmosphere", f"{_pm(j.get('kappa_ppm'), j.get('kappa_sigma_ppm'))} ppm")])]
    parts.append(_rows_table(
        "run-joint-stations", ("station", "shift from its calibration (mm)", "(mrad)",
                               "in the calibration's sigmas"),
        [f"<tr><td class='s'>{html.escape(str(sid))}</td>"
         + ("<td class='s' colspan='3'>held (the reference)</td>" if v.get("held") else
            f"<td>{_vec(v.get('shift_mm'), '.2f')}</td>"
            f"<td>{_vec(v.get('shift_mrad'), '.3f')}</td>"
            f"<td>{_vec(v.get('shift_sigmas'), '.1f')}</td>") + "</tr>"
         for sid, v in (j.get("stations") or {}).items()]))
    sync, clocks = j.get("time_sync") or {}, j.get("clocks") or {}
    rows = []
    for sid in dict.fromkeys([*sync, *clocks]):
        o, c = sync.get(sid) or {}, clocks.get(sid) or {}
        rows.append(f"<tr><td class='s'>{html.escape(str(sid))}</td>"
                    f"<td>{_pm(o.get('offset_ms'), o.get('sigma_ms'))}</td>"
                    + "".join(f"<td>{_fmt(c.get(k), 3)}</td>"
                              for k in ("start_ms", "end_ms", "median_sigma_ms")) + "</tr>")
    ref = html.escape(str(j.get("clock_reference")))
    parts.append(_rows_table(
        "run-joint-clocks", ("station", "constant clock offset (ms)",
                             f"against the reference {ref}: start (ms)", "end (ms)",
                             "median sigma (ms)"), rows))
    parts.append(_rows_table(
        "run-joint-prisms", ("prism", "shift from the survey (mm)", "sigma (mm)",
                             "largest sigma (mm)", "test (sigmas)", "survey",
                             "weight of the move",
                             "a move no station sees: along (body frame), turns the poses by"),
        [f"<tr><td class='s'>{html.escape(str(pid))}</td>"
         f"<td>{_vec(v.get('shift_mm'), '.2f')}</td><td>{_vec(v.get('sigma_mm'), '.2f')}</td>"
         f"<td>{_fmt(v.get('largest_sigma_mm'), 3)}</td><td>{_fmt(v.get('test_sigmas'), 3)}</td>"
         f"<td class='s'>{'moved' if v.get('moved') else 'kept'}</td>"
         f"<td>{_fmt(v.get('moved_weight'), 3)}</td><td class='s'>{_blind_text(v)}</td></tr>"
         for pid, v in (j.get("prisms") or {}).items()]))
    noise, gm = j.get("noise") or {}, j.get("gauss_markov") or {}
    parts.append(_rows_table(
        "run-joint-noise", ("station", "channel", "white: factor of the datasheet's variance",
                            "correlated (Gauss-Markov)"),
        [_joint_noise_row(sid, ch, (noise.get(sid) or {}).get(ch), (gm.get(sid) or {}).get(ch))
         for sid in dict.fromkeys([*noise, *gm]) for ch in ("hz", "v", "d")
         if (noise.get(sid) or {}).get(ch) or (gm.get(sid) or {}).get(ch)]))
    end = {sid: {k: (v.get(k) or [None])[-1] for k in v} for sid, v
           in (j.get("settling") or {}).items()}  # at the last knot
    parts.append(_rows_table(
        "run-joint-settling", ("station", "height change at the end (mm)",
                               "yaw change at the end (″)"),
        [f"<tr><td class='s'>{html.escape(str(sid))}</td>"
         f"<td>{_pm(v.get('height_mm'), v.get('height_sigma_mm'))}</td>"
         f"<td>{_pm(v.get('yaw_arcsec'), v.get('yaw_sigma_arcsec'))}</td></tr>"
         for sid, v in end.items()]))
    ax = j.get("motion_axes")
    if ax:
        parts.append(_kv_table("run-joint-axes", [
            (f"motion axes {a} (mrad)", _pm(r, sd))
            for a, r, sd in zip(ax["axes"], ax["rotation_mrad"], ax["sigma_mrad"], strict=True)]))
    rock = j.get("rocking")
    if rock:
        parts.append(_rows_table(
            "run-joint-rocking", ("axis", "rocking (mm, mrad)", "correlation time (s)",
                                  "determined"),
            [f"<tr><td class='s'>{html.escape(a)}</td>"
             f"<td>{_pm(v.get('sigma'), v.get('sigma_sigma'))}</td>"
             f"<td>{_pm(v.get('tau_s'), v.get('tau_sigma_s'))}</td>"
             f"<td class='s'>{'yes' if v.get('determined') else 'no (its start)'}</td></tr>"
             for a, v in rock.items()]))
        piv = j.get("rocking_pivot_m")
        parts.append(_kv_table("run-joint-pivot", [(
            "rocking's pivot (body frame, m)",
            "the prisms' centroid (not given)" if piv is None
            else html.escape(", ".join(f"{x:.3f}" for x in piv)))]))
    parts.append("<p><small>Each estimate with its sigma; the components the data do not "
                 "determine keep their prior and say so. Method: rtsgt's docs/joint.md."
                 "</small></p>")
    return "".join(parts)


def _distances_html(d: Mapping) -> str:
    rows = "".join(
        f"<tr><td class='s'>{html.escape(str(pair))}</td><td>{_fmt(v.get('surveyed_m'), 5)}</td>"
        f"<td>{_fmt(v.get('median_deviation_mm'), 3)}</td>"
        f"<td>{_fmt(v.get('predicted_sigma_mm'), 3)}</td><td>{_fmt(v.get('ratio'), 3)}</td>"
        f"<td>{_fmt(v.get('poses'))}</td></tr>"
        for pair, v in d.items() if isinstance(v, Mapping))
    if not rows:
        return ""
    return ("<table id='run-distances'><tr><th class='k'>prisms</th><th>surveyed (m)</th>"
            "<th>median deviation (mm)</th><th>predicted sigma (mm)</th><th>ratio</th>"
            f"<th>poses</th></tr>{rows}</table>")


def _timings_html(timings: Mapping, per_row: int = 6) -> str:
    """The seconds of each stage, ``per_row`` stages to a pair of rows."""
    items = [(k, v) for k, v in timings.items() if isinstance(v, (int, float))]
    if not items:
        return ""
    items.append(("total", sum(v for _, v in items)))
    rows = []
    for i in range(0, len(items), per_row):
        chunk = items[i:i + per_row]
        pad = "<td></td>" * (per_row - len(chunk))
        rows.append("<tr>" + "".join(f"<th>{html.escape(k.replace('_', ' '))}</th>"
                                     for k, _ in chunk) + pad.replace("td", "th") + "</tr>")
        rows.append("<tr>" + "".join(f"<td>{v:.2f}</td>" for _, v in chunk) + pad + "</tr>")
    return f"<table id='run-timings'>{''.join(rows)}</table>"


def _run_html(summary: Mapping, summary_href: str | None) -> str:
    """What ``summary.json`` holds that a reader needs, in tables: the run, the options used,
    the filters, the prisms' GP fits, the calibration, the inter-prism distances, the joint
    engine's estimates, the warnings and the timings (s); a link to the file for the rest."""
    if not summary:
        return "<p class='note'>No summary.json in this run.</p>"
    name = "summary.json"
    link = (f"<a href='{html.escape(summary_href, quote=True)}'>{name}</a>" if summary_href
            else f"<code>{name}</code>")
    parts = [_run_info_html(summary)]
    if summary.get("parameters"):
        parts.append(f"<h3>Options used</h3>{_options_html(summary['parameters'])}")
    for title, text in (("Filters", _filters_html(summary.get("filters") or {})),
                        ("Prisms and their GP", _prisms_html(summary.get("prisms") or {})),
                        ("Extrinsic calibration",
                         _calibration_html(summary.get("calibration") or {})),
                        ("Inter-prism distances",
                         _distances_html(summary.get("inter_prism_distances") or {})),
                        ("Joint engine's estimates", _joint_html(summary.get("joint") or {}))):
        if text:
            parts.append(f"<h3>{title}</h3>{text}")
    warns = summary.get("warnings") or []
    if warns:
        parts.append(f"<h3>Warnings ({len(warns)})</h3><ul id='run-warnings'>"
                     + "".join(f"<li>{html.escape(str(w))}</li>" for w in warns) + "</ul>")
    timings = _timings_html(summary.get("timings_s") or {})
    if timings:
        parts.append(f"<h3>Timings (s)</h3>{timings}")
    parts.append(f"<p>Every number of the run, with the calibration's matrices and coupling, "
                 f"the GCPs' positions and each self-check's details, is in {link}.</p>")
    return "".join(parts)


def figure_html(fig: DrawnFigure, fmt: str) -> str:
    """A drawn figure as an HTML ``<figure>``, its image a data URI in ``fmt`` (svg, png)."""
    FigureCanvasAgg(fig.figure)
    buf = io.BytesIO()
    fig.figure.savefig(buf, format=fmt, dpi=110, bbox_inches="tight",
                       metadata={"Date": None} if fmt == "svg" else None)
    mime = "image/svg+xml" if fmt == "svg" else "image/png"
    b64 = base64.b64encode(buf.getvalue()).decode("ascii")
    alt = html.escape(fig.caption or fig.name)
    return (f"<figure id='fig-{fig.name}'><img alt='{alt}' src='data:{mime};base64,{b64}'>"
            f"<figcaption>{html.escape(fig.caption)}</figcaption></figure>")


def ellipsoid_mesh(centres: np.ndarray, covs: np.ndarray, scale: float, *,
                   n_lat: int = 8, n_lon: int = 12, k2: float = CHI2_3_95):
    """Triangle mesh of the ellipsoids ``(x - c)^T S^-1 (x - c) = k2`` (default the 95 % quantile
    of chi-square(3)) of ``centres`` (E, 3) and ``covs`` (E, 3, 3), m^2, magnified by ``scale``,
    from a unit sphere of ``n_lat`` rings and ``n_lon`` meridians: ``vertices`` (E V, 3),
    ``faces`` (E F, 3) vertex indices, and each vertex's ellipsoid (E V,)."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.outer(np.sin(th), np.cos(ph)), np.outer(np.sin(th), np.sin(ph)),
                     np.outer(np.cos(th), np.ones_like(ph))], axis=-1).reshape(-1, 3)
    unit = np.vstack([[0, 0, 1.0], ring, [0, 0, -1.0]])  # V = 2 + (n_lat - 1) n_lon
    V = unit.shape[0]
    faces = []
    nr = n_lat - 1
    for j in range(n_lon):  # top and bottom caps
        j2 = (j + 1) % n_lon
        faces.append((0, 1 + j, 1 + j2))
        faces.append((V - 1, 1 + (nr - 1) * n_lon + j2, 1 + (nr - 1) * n_lon + j))
    for i in range(nr - 1):
        for j in range(n_lon):
            j2 = (j + 1) % n_lon
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + j2
            c, d = a + n_lon, b + n_lon
            faces += [(a, c, b), (b, c, d)]
    faces = np.asarray(faces)
    w, U = np.linalg.eigh(0.5 * (covs + np.swapaxes(covs, -1, -2)))
    A = U * np.sqrt(np.clip(w, 0.0, None) * k2)[:, None, :] * scale  # (E, 3, 3)
    verts = centres[:, None, :] + np.einsum("eij,vj->evi", A, unit)
    E = centres.shape[0]
    all_faces = (faces[None] + (np.arange(E) * V)[:, None, None]).reshape(-1, 3)
    return verts.reshape(-1, 3), all_faces, np.repeat(np.arange(E), V)


def scene_box(points: np.ndarray, margin: float = SCENE_MARGIN,
              min_height: float = SCENE_MIN_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """Axis ranges (3, 2), m, and aspect ratio (3,) of a 3D scene at one scale holding every
    ``points`` (N, 3) row without NaN: ``margin`` of the largest extent added on each side, the z
    range at least ``min_height`` of it."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.size == 0:
        p = np.zeros((1, 3))
    lo, hi = p.min(axis=0), p.max(axis=0)
    side = max(float(np.max(hi - lo)), 1.0)
    half = (hi - lo) / 2 + margin * side
    half[2] = max(half[2], min_height * side / 2)
    centre = (lo + hi) / 2
    ranges = np.column_stack([centre - half, centre + half])
    return ranges, half / half.max()


def _view3d(data: RunRecord, max_ellipsoids: int, scale: float | None):
    """The plotly div (with plotly.js inline), the number of ellipsoids and their scale."""
    fig, n_ell, used_scale = view3d_figure(data, max_ellipsoids, scale)
    if fig is None:
        return None, 0, None
    div = fig.to_html(
        include_plotlyjs=True, full_html=False, div_id=VIEW3D_ID,
        config={"displaylogo": False, "responsive": True},
        default_height="720px",
        post_script=("var gd=document.getElementById('{plot_id}');"
                     "gd.setAttribute('data-rendered','1');"),
    )
    return div, n_ell, used_scale


def view3d_figure(data: RunRecord, max_ellipsoids: int = 150, scale: float | None = None):
    """The interactive 3D view of a run ``data``: the plotly figure (None without plotly), the
    number of 95 % position ellipsoids drawn (at most ``max_ellipsoids``, spread over the kept
    poses) and their magnification ``scale`` (default: the median one about 1 % of the scene;
    None without ellipsoids)."""
    try:
        import plotly.graph_objects as go
    except ImportError:
        return None, 0, None
    traces = []
    gt = data.groundtruth
    everything = []
    for pid, tr in data.measurements.items():
        step = max(1, len(tr) // 4000)
        p = tr.xyz[::step]
        traces.append(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers",
                                   marker=dict(size=1.5, opacity=0.5),
                                   name=f"prism {pid} measurements"))
        everything.append(tr.xyz)
    n_ell, used_scale = 0, None
    if len(gt):
        path = break_gaps(gt.t, gt.position)
        lever = body_origin_offset(data)
        traces.append(go.Scatter3d(x=path[:, 0], y=path[:, 1], z=path[:, 2], mode="lines",
                                   line=dict(color="black", width=4),
                                   name="ground truth (body origin" + (
                                       f", {lever:.1f} m from the prisms' centroid)"
                                       if lever >= 0.5 else ")")))
        everything.append(gt.position)
    everything += [p[None] for p in data.stations.values()]
    marks, points = _marker_traces(go, data)
    traces += marks
    shown = everything + points  # everything drawn, which the scene's box holds
    if len(gt) and gt.cov is not None and max_ellipsoids > 0:
        mesh = _ellipsoids_trace(go, gt, everything, max_ellipsoids, scale)
        if mesh is not None:
            traces.append(mesh[0])
            shown.append(mesh[1])
            n_ell, used_scale = mesh[2], mesh[3]
    ranges, aspect = scene_box(np.concatenate(shown) if shown else np.zeros((1, 3)))
    fig = go.Figure(traces)
    fig.update_layout(**_scene_layout(data.name, ranges, aspect, used_scale))
    return fig, n_ell, used_scale


def _marker_traces(go, data: RunRecord) -> tuple[list, list]:
    """The 3D view's stations, GCPs and rejected poses (one trace per gate), and the points
    (n, 3) drawn (GCPs, rejected) for the scene's box."""
    traces, shown = [], []
    if data.gcp_xyz is not None and len(data.gcp_xyz):
        shown.append(data.gcp_xyz)
    if data.stations:
        st = np.array(list(data.stations.values()))
        where = ("top right", "bottom left", "top left", "bottom right", "top center",
                 "bottom center")  # stations often stand close together: spread the labels
        traces.append(go.Scatter3d(x=st[:, 0], y=st[:, 1], z=st[:, 2], mode="markers+text",
                                   text=[f"station {s}" for s in data.stations],
                                   textposition=[where[k % len(where)]
                                                 for k in range(len(data.stations))],
                                   marker=dict(size=6, symbol="diamond", color="#E69F00"),
                                   name="stations"))
    if data.gcp_xyz is not None and len(data.gcp_xyz):
        g = data.gcp_xyz
        traces.append(go.Scatter3d(x=g[:, 0], y=g[:, 1], z=g[:, 2], mode="markers",
                                   marker=dict(size=3, symbol="square", color="#666"),
                                   name="ground control points"))
    # rejected poses where the body origin was (the reference fitted onto the prisms), as in
    # the top view, one trace per gate
    pos_r, reason_r = rejected_positions(data)
    shown.append(pos_r)
    for reason in sorted(set(reason_r.tolist())):
        c = pos_r[reason_r == reason]
        traces.append(go.Scatter3d(x=c[:, 0], y=c[:, 1], z=c[:, 2], mode="markers",
                                   marker=dict(size=4, symbol="x", color="#D55E00"),
                                   name=f"rejected: {reason or 'unspecified'} ({len(c)})"))
    return traces, shown


def _scene_layout(name: str, ranges: np.ndarray, aspect: np.ndarray, scale) -> dict:
    """The 3D view's layout: axes holding every point drawn at one scale (plotly's aspectmode
    "data" would size the box to a volume of one and cut a long, flat site off the view)."""
    axis = dict(autorange=False)
    return dict(
        scene=dict(aspectmode="manual",
                   aspectratio=dict(x=aspect[0], y=aspect[1], z=aspect[2]),
                   xaxis=dict(axis, range=ranges[0].tolist(), title="x (m)"),
                   yaxis=dict(axis, range=ranges[1].tolist(), title="y (m)"),
                   zaxis=dict(axis, range=ranges[2].tolist(), title="z (m)"),
                   camera=dict(eye=dict(zip("xyz", CAMERA_EYE, strict=True)))),
        margin=dict(l=0, r=0, t=30, b=0),
        legend=dict(x=0, y=1, bgcolor="rgba(255,255,255,.8)", itemsizing="constant"),
        title=dict(text=f"{name}: world frame; ellipsoids magnified {scale or 1:g} x",
                   font=dict(size=13)),
    )


def _ellipsoids_trace(go, gt, everything: list, max_ellipsoids: int, scale: float | None):
    """The mesh of the 95 % position ellipsoids of at most ``max_ellipsoids`` kept poses, its
    vertices, their number and magnification (default: the median 1 % of the extent of
    ``everything``); None without a finite covariance."""
    ok = np.flatnonzero(np.all(np.isfinite(gt.cov[:, :3, :3]), axis=(1, 2)))
    if not ok.size:
        return None
    sel = ok[np.unique(np.linspace(0, ok.size - 1, min(ok.size, max_ellipsoids))
                       .round().astype(int))]
    covs = gt.cov[sel, :3, :3]
    if scale is None:
        allp = np.concatenate(everything)
        allp = allp[np.all(np.isfinite(allp), axis=1)]
        extent = max(float(np.max(np.ptp(allp, axis=0))), 1.0)
        radius = np.sqrt(CHI2_3_95 * np.linalg.eigvalsh(covs)[:, -1])
        med = float(np.median(radius))
        scale = nice_scale(0.01 * extent / med) if med > 0 else 1.0
    verts, faces, which = ellipsoid_mesh(gt.position[sel], covs, scale)
    sig_mm = np.sqrt(np.trace(covs, axis1=1, axis2=2)) * 1e3
    mesh = go.Mesh3d(
        x=verts[:, 0], y=verts[:, 1], z=verts[:, 2],
        i=faces[:, 0], j=faces[:, 1], k=faces[:, 2],
        intensity=sig_mm[which], colorscale="Viridis", opacity=0.55,
        colorbar=dict(title=dict(text="sqrt(tr Σ)<br>(mm)"), len=0.6),
        name=f"95 % position ellipsoids x {scale:g}", showlegend=True,
        hoverinfo="name")
    return mesh, verts, int(sel.size), float(scale)


def _kpis(data: RunRecord, a: Analysis) -> str:
    n_kept = len(data.groundtruth)
    n_rej = int(data.rejected_t.size)
    items = [
        ("kept poses", f"{n_kept}"),
        ("rejected poses", f"{n_rej}"),
        ("measurements", f"{a.n_measurements}"),
        ("median pose translation", f"{_fmt(a.pose_median_translation_mm.get('all'), 3)} mm"),
        ("median pose rotation", f"{_fmt(a.pose_median_rotation_mrad.get('all'), 3)} mrad"),
        ("median prism sqrt(||Σ||F)", f"{_fmt(a.median_mm.get('all'), 3)} mm"),
    ]
    if data.prior:  # each prism's GP motion prior (WNOA: the paper's; WNOJ: on the jerk)
        items.append(("GP prior per prism", ", ".join(
            f"{pid}: {p.upper()}" for pid, p in data.prior.items())))
    n_left = int(np.sum(data.removed.stage == "module4"))
    if n_left:  # measurements inside windows of distance rejections, out of the GP fits
        items.insert(3, ("measurements left out (distance windows)", f"{n_left}"))
    if n_kept > 1:
        dur = float(data.groundtruth.t[-1] - data.groundtruth.t[0])
        items.insert(0, ("span of the ground truth", f"{dur:.0f} s"))
    return "<div class='kpi'>" + "".join(f"<div>{html.escape(k)}<b>{v}</b></div>"
                                         for k, v in items) + "</div>"


def render_report(data: RunRecord, analysis: Analysis, *,
                  figures: Mapping[str, DrawnFigure] | None = None,
                  figure_format: str = "svg", max_ellipsoids: int = 150,
                  ellipsoid_scale: float | None = None,
                  summary_href: str | None = None) -> tuple[str, dict]:
    """The report page of ``data`` and its ``analysis`` as a string, and what it holds
    (``figures``, ``view3d``, ``n_ellipsoids``, ``ellipsoid_scale``): ``figures`` to embed
    (default :func:`rtsgt.report.figures.draw_all`) in ``figure_format`` (svg, png), the 3D
    view's ellipsoids as :func:`view3d_figure`, and the link ``summary_href`` to the run's
    ``summary.json`` (relative; without it the file is named, not linked)."""
    if figure_format not in ("svg", "png"):
        raise ValueError(f"Expected figure_format 'svg' or 'png', got {figure_format!r}")
    figs = draw_all(data, analysis) if figures is None else figures
    div, n_ell, scale = _view3d(data, max_ellipsoids, ellipsoid_scale)
    title = f"rtsgt report: {data.name}"
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    where = f" from <code>{html.escape(str(data.path))}</code>" if data.path else ""
    if div is None:
        view = ("<p class='note' id='no-view3d'>The interactive 3D view needs plotly: "
                "<code>pip install 'rtsgt[report]'</code>, then run <code>rtsgt report</code> "
                "again.</p>")
    else:
        view = ("<p class='print-only'>The 3D view is interactive: open the HTML file in a "
                "browser (the top view above shows the site from above).</p>"
                "<p class='screen-only'>Drag to rotate, scroll to zoom, double-click to reset. "
                "The ellipsoids are the 95 % regions (chi-square 3 dof) of the position "
                f"covariance of {n_ell} poses spread evenly over the kept ones, <b>magnified "
                f"{scale:g} times</b> about their centres so that they are visible at the scale "
                f"of the site; their colour is sqrt(tr Σ) in mm.</p>{div}")
    fig_html = "".join(figure_html(f, figure_format) for f in figs.values())
    body = f"""<main>
<header><h1>{html.escape(title)}</h1>
<p>Generated {now} by rtsgt {html.escape(__version__)}{where}.</p>
<nav><a href="#verdict">verdict</a><a href="#key">key numbers</a><a href="#checks">self-checks</a>
<a href="#sources">noise sources</a>
<a href="#pose">pose</a><a href="#figures">figures</a><a href="#view">3D view</a>
<a href="#run">the run</a></nav></header>
{_verdict_html(data)}
<section id="key"><h2>Key numbers</h2>{_kpis(data, analysis)}</section>
<section id="checks"><h2>Self-checks: what the data say about the uncertainty</h2>
{_self_checks_html(data.self_checks)}{_correlated_noise_html(data.correlated_noise)}</section>
<section id="sources"><h2>Noise sources at the prisms, next to the paper</h2>
{_sources_table(analysis)}</section>
<section id="pose"><h2>Pose uncertainty per noise source</h2>{_pose_table(analysis)}</section>
<section id="figures"><h2>Figures</h2>{fig_html}</section>
<section id="view"><h2>Interactive 3D view</h2>{view}</section>
<section id="run"><h2>The run: inputs, options, timings</h2>
{_run_html(data.summary, summary_href)}</section>
<footer><p><small>Method: {html.escape(PAPER_CITATION)}.</small></p></footer>
</main>"""
    page = (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head>"
            f"<body>{body}</body></html>\n")
    info = {"figures": tuple(figs), "view3d": div is not None, "n_ellipsoids": n_ell,
            "ellipsoid_scale": scale}
    return page, info


def _verdict_html(data: RunRecord) -> str:
    """The run's verdict (:mod:`rtsgt.checks.verdict`) with every finding, worst first."""
    v = record_verdict(data)
    words = {2: "not usable as is", 1: "caveat", 0: "note"}
    items = "".join(f"<li><b>{words[f.severity]}</b> ({html.escape(f.check)}): "
                    f"{html.escape(f.text)}</li>" for f in v.findings)
    return (f"<section id='verdict'><h2>Verdict: {html.escape(v.level)}</h2>"
            + (f"<ul>{items}</ul>" if items else "<p>Every self-check passed.</p>")
            + "</section>")


def _relative_href(target: Path, folder: Path) -> str:
    """A URL path to ``target`` relative to ``folder`` (a ``file:`` URI when there is none,
    e.g. another drive)."""
    try:
        rel = Path(os.path.relpath(target.resolve(), folder.resolve()))
    except ValueError:
        return target.resolve().as_uri()
    return urllib.parse.quote(rel.as_posix())


def is_report_html(head: str) -> bool:
    """Whether a file's first characters are those of an rtsgt report page."""
    return head.startswith("<!DOCTYPE html>") and "<title>rtsgt report: " in head


def write_report_file(data: RunRecord, analysis: Analysis, path: str | PathLike,
                      **kwargs) -> ReportInfo:
    """Write the report of ``data`` and ``analysis`` to ``path`` (atomically).

    Keyword arguments as :func:`render_report`; ``summary_href`` defaults to the path of
    ``data.path / "summary.json"`` relative to the page's folder.
    """

    p = Path(path)
    if "summary_href" not in kwargs and data.path is not None:
        kwargs["summary_href"] = _relative_href(Path(data.path) / "summary.json", p.parent)
    page, info = render_report(data, analysis, **kwargs)
    if not info["view3d"]:
        warnings.warn("plotly is not installed: the report has no interactive 3D view "
                      "(pip install 'rtsgt[report]')", RtsgtWarning, stacklevel=2)
    p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(p, page)
    return ReportInfo(p, p.stat().st_size, tuple(info["figures"]), bool(info["view3d"]),
                      int(info["n_ellipsoids"]), info["ellipsoid_scale"])


def write_report(run_dir: str | PathLike, out: str | PathLike | None = None, *,
                 bins: Sequence[float] | str = DEFAULT_BINS_M, engine: str | None = None,
                 samples: int | None = None, pose_measure: str = "sqrt_trace",
                 shown_path: str | PathLike | None = None, **kwargs) -> Path:
    """Read a run directory ``run_dir``, analyse it (``bins``, ``engine``, ``samples``,
    ``pose_measure`` as :func:`rtsgt.report.analysis.analyze`) and write its report to ``out``
    (default ``RUN_DIR/report.html``); ``shown_path``: the run's path as the page states it;
    ``kwargs`` as :func:`render_report`. Returns the written file."""
    data = read_run(run_dir)
    if shown_path is not None:
        data = dataclasses.replace(data, path=Path(shown_path))
    analysis = analyze(data, bins=bins, engine=engine, samples=samples,
                       pose_measure=pose_measure)
    path = Path(run_dir) / "report.html" if out is None else Path(out)
    # the link to summary.json from where the page is, before the run directory is renamed
    kwargs.setdefault("summary_href", _relative_href(Path(run_dir) / "summary.json",
                                                     path.parent))
    return write_report_file(data, analysis, path, **kwargs).path
