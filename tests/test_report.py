"""Figures, the HTML report (in a real headless Chromium), and `rtsgt analyze` / `rtsgt report`.

The figures are checked for content: the number of boxes is sources x non-empty bins (plus
the all-ranges group), each box holds the values of its group and draws their median, every
measurement is plotted, the ellipses are the 95 % ellipses of the covariances at the stated
magnification, every measurement gap is shaded. The report is opened in Debian's Chromium
through the DevTools protocol (over ``--remote-debugging-pipe``, no extra Python package): no
console error, no network request, the plotly 3D view renders (a WebGL canvas with drawn
pixels) and can be rotated; screenshots are saved for inspection.
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.patches import Ellipse, PathPatch
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.io.run_dir import read_run
from rtsgt.report.analysis import ALL, analyze
from rtsgt.report.figures import (
    CHI2_2_95,
    FIGURE_NAMES,
    default_gap_s,
    draw_all,
    plot_pose_uncertainty,
    plot_source_norms,
    plot_top_view,
    plot_uncertainty_time,
    save_figures,
)
from rtsgt.report.html import CHI2_3_95, VIEW3D_ID, ellipsoid_mesh, render_report

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _paths import EXAMPLE_TOML as EXAMPLE  # noqa: E402
from test_analysis import make_run_data, write_run_dir  # noqa: E402

runner = CliRunner()
#: Where the browser test leaves its screenshots for inspection (besides its tmp_path).
SCREENSHOT_DIR = Path(tempfile.gettempdir()) / "rtsgt-test-report"


@pytest.fixture(scope="module")
def data():
    return make_run_data()


@pytest.fixture(scope="module")
def analysis(data):
    return analyze(data)


# --------------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------------


def test_source_norm_boxes_match_the_data(analysis):
    a = analysis
    f = plot_source_norms(a)
    groups = [k for k, c in enumerate(a.bin_counts) if c > 0]
    assert len(groups) == 3
    assert f.boxes["norms"] == len(a.sources) * (len(groups) + 1)  # + all ranges
    ax = f.figure.axes[1]
    assert len([p for p in ax.patches if isinstance(p, PathPatch)]) == f.boxes["norms"]
    for (s, group), n, med in zip(f.box_keys["norms"], f.box_sizes["norms"],
                                  f.box_medians["norms"], strict=True):
        if group == "all ranges":
            vals = a.norm_mm[s]
        else:
            vals = a.norm_mm[s][a.bin_index == a.bin_labels.index(group)]
        assert n == vals.size
        assert med == pytest.approx(np.median(vals), rel=1e-12)
    # every measurement is in exactly one bin box per source
    assert sum(f.box_sizes["norms"]) == 2 * len(a.sources) * a.n_measurements
    # the paper's medians: 5 overall + instrument > 150 m + calibration in 3 bins
    assert f.points["paper medians"] == 9
    shares = [p.get_height() for p in f.figure.axes[0].patches]
    np.testing.assert_allclose(shares, 100 * np.array(a.bin_shares))


def test_source_norms_skip_empty_bins(data):
    a = analyze(data, bins="0,75,150,1000")
    f = plot_source_norms(a)
    assert a.bin_counts[3] == 0
    assert f.boxes["norms"] == len(a.sources) * 4  # 3 non-empty bins + all ranges


def test_pose_uncertainty_boxes(analysis):
    f = plot_pose_uncertainty(analysis)
    n = len(analysis.pose_sources)
    assert f.boxes == {"translation": n, "rotation": n}
    for panel, values in (("translation", analysis.translation_mm),
                          ("rotation", analysis.rotation_mrad)):
        assert [k[0] for k in f.box_keys[panel]] == list(analysis.pose_sources)
        assert f.box_sizes[panel] == [analysis.pose_t.size] * n
        np.testing.assert_allclose(f.box_medians[panel],
                                   [np.median(values[s]) for s in analysis.pose_sources])
    for ax in f.figure.axes:
        assert len([p for p in ax.patches if isinstance(p, PathPatch)]) == n
        assert "(mm)" in ax.get_ylabel() or "(mrad)" in ax.get_ylabel()


def test_top_view_content(data):
    f = plot_top_view(data, max_ellipses=40)
    ax = f.figure.axes[0]
    lines = {ln.get_label(): ln for ln in ax.lines}
    for pid, tr in data.measurements.items():
        ln = lines[f"prism {pid} measurements"]
        np.testing.assert_array_equal(ln.get_xdata(), tr.xyz[:, 0])
        assert f.points[f"prism {pid}"] == len(tr)
    gt = lines["ground truth (body origin)"]
    assert np.count_nonzero(np.isfinite(gt.get_xdata())) == len(data.groundtruth)
    ell = [p for p in ax.patches if isinstance(p, Ellipse)]
    assert len(ell) == f.ellipses == 40
    # the first ellipse is the 95 % ellipse of the first pose, magnified by the stated scale
    c = data.groundtruth.cov[0, :2, :2]
    w = np.linalg.eigvalsh(c)
    e0 = ell[0]
    assert e0.width == pytest.approx(2 * np.sqrt(CHI2_2_95 * w[1]) * f.ellipse_scale)
    assert e0.height == pytest.approx(2 * np.sqrt(CHI2_2_95 * w[0]) * f.ellipse_scale)
    np.testing.assert_allclose(e0.center, data.groundtruth.position[0, :2])
    assert f.ellipse_scale in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000)
    assert f"x {f.ellipse_scale:g}" in lines[next(k for k in lines if "ellipses" in k)].get_label()
    assert f.points["stations"] == 3 and f.points["ground control points"] == 3
    reasons = sorted(set(data.rejected_reason))
    assert sum(f.points[f"rejected: {r}"] for r in reasons) == data.rejected_t.size
    assert ax.get_xlabel().endswith("(m)") and ax.get_ylabel().endswith("(m)")
    f2 = plot_top_view(data, ellipse_scale=3.0)
    assert f2.ellipse_scale == 3.0 and f2.ellipses == 60


def test_uncertainty_time_content(data):
    f = plot_uncertainty_time(data)
    assert default_gap_s(data) == pytest.approx(3.0, rel=0.02)  # 3 x the 1 s spacing
    # prism 2 has two 5 s gaps; the others have none
    assert f.spans == 2
    for ax in f.figure.axes:
        assert len(ax.patches) == 2
    ax0 = f.figure.axes[0]
    lines = {ln.get_label(): ln for ln in ax0.lines}
    T = data.prisms_t.size
    for i, pid in enumerate(data.prism_ids):
        y = np.asarray(lines[f"prism {pid}"].get_ydata(), dtype=float)
        assert np.count_nonzero(np.isfinite(y)) == T
        expect = np.sqrt(np.trace(data.prisms_cov[:, i], axis1=1, axis2=2)) * 1e3
        np.testing.assert_allclose(y[np.isfinite(y)], expect)
    assert f.points["pose translation"] == len(data.groundtruth)
    assert f.points["rejected poses"] == data.rejected_t.size
    assert "UTC" in f.figure.axes[-1].get_xlabel()
    assert f.common_spans == 0


def test_uncertainty_time_shades_common_gaps_once(data):
    """A window where no prism is measured: one grey span, on top of each prism's gap."""
    from dataclasses import replace

    t0 = data.prisms_t[0]
    cut = {}
    for pid, tr in data.measurements.items():
        keep = ~((tr.t - t0 > 100) & (tr.t - t0 < 110))
        cut[pid] = type(tr)(tr.t[keep], tr.xyz[keep], tr.cov[keep],
                            {s: c[keep] for s, c in tr.cov_by_source.items()}, tr.prism,
                            tr.frame, tr.station, tr.range_m[keep])
    f = plot_uncertainty_time(replace(data, measurements=cut))
    assert f.spans == 2 + 3 and f.common_spans == 1
    for ax in f.figure.axes:
        assert len(ax.patches) == 2 + 3 + 1
        grey = [p for p in ax.patches if p.get_facecolor()[:3] == pytest.approx(
            (0xd4 / 255,) * 3)]
        assert len(grey) == 1
        x = grey[0].get_x() + t0
        # the common gap runs from the last measurement before the cut to the first after it
        last = max(tr.t[tr.t - t0 <= 100].max() for tr in cut.values())
        first = min(tr.t[tr.t - t0 >= 110].min() for tr in cut.values())
        assert x == pytest.approx(last) and grey[0].get_width() == pytest.approx(first - last)
    labels = [ln.get_label() for ln in f.figure.axes[0].lines]
    assert "no prism measured" in labels


def test_station_labels_do_not_collide():
    from rtsgt.report.figures import _label_offsets

    # three stations within a few metres (the real excerpt): three different directions
    off = _label_offsets(np.array([[0.0, 0.0], [-0.66, -1.3], [0.87, -2.43]]))
    ang = np.sort(np.degrees(np.arctan2(off[:, 1], off[:, 0])) % 360)
    gaps = np.diff(np.r_[ang, ang[0] + 360])
    assert gaps.min() > 60
    same = _label_offsets(np.zeros((3, 2)))  # even at one place
    assert len({tuple(np.round(o, 6)) for o in same}) == 3
    assert _label_offsets(np.zeros((0, 2))).shape == (0, 2)


def test_save_png_and_svg(data, analysis, tmp_path):
    figs = draw_all(data, analysis)
    assert tuple(figs) == FIGURE_NAMES
    paths = save_figures(figs, tmp_path)
    assert sorted(p.name for p in paths) == sorted(f"{n}.{e}" for n in FIGURE_NAMES
                                                   for e in ("png", "svg"))
    img = mpimg.imread(tmp_path / "source_norms.png")
    assert img.shape[0] > 500 and img.shape[1] > 800
    assert img[..., :3].std() > 0.05  # not a blank canvas
    root = ET.parse(tmp_path / "source_norms.svg").getroot()
    assert root.tag.endswith("svg")
    text = (tmp_path / "source_norms.svg").read_text()
    assert "range from the station (m)" in text and "share (%)" in text


# --------------------------------------------------------------------------------------------
# HTML report, static checks
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def report_page(data, analysis):
    return render_report(data, analysis)


def test_report_is_self_contained(report_page, data, analysis):
    page, info = report_page
    assert info["view3d"] and info["n_ellipsoids"] == len(analysis.pose_t)
    external = re.findall(r"<(?:script|link|img|iframe|source)\b[^>]*\b(?:src|href)\s*=\s*"
                          r"[\"']?(?:https?:)?//", page, flags=re.I)
    assert external == []
    assert page.count("<img alt=") == 4
    assert page.count("src='data:image/svg+xml;base64,") == 4
    assert f'id="{VIEW3D_ID}"' in page
    assert "Plotly.newPlot" in page and len(page) > 3_000_000  # plotly.js is inline
    assert f"magnified {info['ellipsoid_scale']:g} times" in page
    assert f"covariance of {info['n_ellipsoids']} poses" in page
    for reason in set(data.rejected_reason):  # rejected poses by gate in the 3D view
        n = int(np.sum(data.rejected_reason == reason))
        assert f'"name":"rejected: {reason} ({n})"' in page


def test_report_tables(report_page, analysis):
    page, _ = report_page
    table = page[page.index("<table id='sources-table'>"):]
    table = table[:table.index("</table>")]
    for v in ("2.1", "2.78", "0.91", "1.88", "5.49", "1.32", "0.4", "0.16", "0.06"):
        assert f"<td class='paper'>{v}</td>" in table
    assert f"<td>{analysis.median_mm['instrument']:.3g}</td>" in table
    pose = page[page.index("<table id='pose-table'>"):]
    assert f"{analysis.pose_median_translation_mm[ALL]:.3g}" in pose[:pose.index("</table>")]


#: A summary.json as rtsgt.io.run_dir writes it, cut to a few keys of each kind.
SUMMARY = {
    "schema": {"name": "rtsgt-run", "version": 1},
    "software": {"name": "rtsgt", "version": "9.9.9"},
    "deployment": "<script>alert(1)</script>",
    "inputs": {"config": "/data/site A/deployment.toml"},
    "parameters": {"engine": "linear", "samples": 1000, "rate_hz": 5.0,
                   "noise_sources": ["instrument", "tilt"], "a_future_option": "kept",
                   "filter": {"tau_r": 2.0, "tau_s": 3.0}},
    "filters": {"module1_station1": {"module": "module1", "n_in": 215, "n_kept": 211,
                                     "removed": {"status": 0, "rate_hz": 4},
                                     "per_series": [{"status": 0, "rate_hz": 4}]}},
    "poses": {"queried": 480, "kept": 470, "rejected_by_reason": {"distance": 10},
              "first_t": 1668095037.6, "last_t": 1668095167.8},
    "prisms": {"1": {"station": "1", "measurements_used": 194, "prior": "wnoa",
                     "qc_m2_s3": [[0.00624, 0, 0], [0, 0.00823, 0], [0, 0, 0.000116]],
                     "qc_fit": {"method": "loo", "loo_nees_per_dof": 1.028,
                                "motion_prior": {"chosen": "classes"}},
                     "median_sigma_mm": 3.498}},
    "calibration": {"reference_station": "1", "method": "gcp", "model": "6dof",
                    "stations": {"2": {"matrix": [[1, 0, 0, 0]] * 4, "yaw_deg": 159.936,
                                       "translation_m": [-0.6586, -1.3012, 0.2864],
                                       "sigma_translation_mm": [0.675, 0.621, 0.568],
                                       "sigma_rotation_mrad": [0.0259, 0.0242, 0.0101]}},
                    "residuals_mm": {"median": 1.9, "max": 8.25, "count": 36},
                    "coupling": {"cross_covariance": {"2|3": [[4.7e-07] * 6] * 6}}},
    "warnings": ["self-check, GCP fit of station 2: variance factor 27.54 <too large>"],
    "timings_s": {"filter_module1": 0.0012, "calibration": 0.0805, "interpolation": 1.498,
                  "pose": 0.042, "gates": 0.0025, "static_noise": 0.113,
                  "self_checks": 1.162},
}


def _element(page: str, start: str, end: str = "</table>") -> str:
    """The text of the element of ``page`` that begins with ``start``."""
    part = page[page.index(start):]
    return part[:part.index(end) + len(end)]


def test_report_run_section_is_tables_not_a_dump(data, analysis):
    """Issue 26: no flat dump of summary.json (half the printed pages); the options, filters,
    prisms, calibration, warnings and timings in readable tables, a link to the file."""
    from dataclasses import replace

    page, _ = render_report(replace(data, summary=SUMMARY), analysis, figures={},
                            summary_href="summary.json")
    assert "<section id=\"summary\">" not in page and "class='summary'" not in page
    for flat in ("qc_fit.method", "stations.2.matrix", "coupling.cross_covariance",
                 "per_series", "filters.module1", "timings_s."):  # dotted keys of the dump
        assert flat not in page, flat
    assert "4.7e-07" not in page  # the coupling matrices stay in the file
    run = _element(page, "<section id=\"run\">", "</section>")
    assert "<a href='summary.json'>summary.json</a>" in run
    assert "<script>alert(1)</script>" not in page  # escaped
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in run and "&lt;too large&gt;" in run
    options = _element(run, "<table id='run-options'")
    assert options.count("<tr>") == len(SUMMARY["parameters"])  # one row per option
    assert "pose engine <small>(engine)</small></th><td class='s'>linear</td>" in options
    assert "<td class='s'>instrument, tilt</td>" in options
    assert "a_future_option" in options and ">kept</td>" in options
    assert "tau_r 2 m/s, tau_s 3 s" in options  # thresholds with their units
    filters = _element(run, "<table id='run-filters'")
    assert "<td class='s'>module 1, station 1</td><td>215</td><td>211</td>" in filters
    assert "rate_hz 4" in filters and "status" not in filters  # reasons that removed some
    prisms = _element(run, "<table id='run-prisms'")
    assert "0.00624, 0.00823, 0.000116" in prisms and "m²/s³" in prisms and "1.03" in prisms
    cal = _element(run, "<table id='run-calibration'")
    assert "159.936" in cal and "-0.659, -1.301, 0.286" in cal
    assert "GCP residuals: median 1.9 mm, largest 8.25 mm over 36" in run
    info = _element(run, "<table id='run-info'")
    assert "2022-11-10 15:43:57 UTC" in info and "470 kept of 480; rejected: distance 10" in info
    assert "<code>/data/site A/deployment.toml</code>" in info and "rtsgt 9.9.9" in info
    timings = _element(run, "<table id='run-timings'")
    assert timings.count("<tr>") == 4  # 7 stages and the total, 6 to a pair of rows
    for stage, v in SUMMARY["timings_s"].items():
        assert f"<th>{stage.replace('_', ' ')}</th>" in timings
        assert f"<td>{v:.2f}</td>" in timings
    assert f"<td>{sum(SUMMARY['timings_s'].values()):.2f}</td>" in timings
    # without a summary: a note; without a link target: the file is named
    assert "No summary.json in this run" in render_report(replace(data, summary={}), analysis,
                                                          figures={})[0]
    page, _ = render_report(replace(data, summary=SUMMARY), analysis, figures={})
    assert "<code>summary.json</code>" in page and "href='summary.json'" not in page


def test_report_links_summary_json_from_where_it_is(data, analysis, tmp_path):
    from dataclasses import replace

    from rtsgt.report.html import write_report_file

    d = replace(data, summary=SUMMARY, path=tmp_path / "run dir")
    page = write_report_file(d, analysis, tmp_path / "run dir" / "report.html",
                             figures={}).path.read_text()
    assert "<a href='summary.json'>" in page
    page = write_report_file(d, analysis, tmp_path / "elsewhere" / "r.html",
                             figures={}).path.read_text()
    assert "<a href='../run%20dir/summary.json'>" in page


def test_view3d_axes_hold_the_whole_path(data):
    """Issue 26: the 3D view cut the start of the path off (plotly's aspectmode "data" sizes
    the box to a volume of one: 2.2 x 2.8 x 0.16 on the real excerpt). The axes' ranges now
    hold every point drawn with a margin, at one scale, the longest side 1."""
    from rtsgt.report.html import SCENE_MARGIN, scene_box, view3d_figure

    fig, n_ell, scale = view3d_figure(data)
    sc = fig.layout.scene
    assert sc.aspectmode == "manual"
    ranges = np.array([sc.xaxis.range, sc.yaxis.range, sc.zaxis.range])
    assert not any(a.autorange for a in (sc.xaxis, sc.yaxis, sc.zaxis))
    drawn = [data.groundtruth.position, data.gcp_xyz, np.array(list(data.stations.values())),
             *(tr.xyz for tr in data.measurements.values())]
    for p in drawn:
        assert np.all((p >= ranges[:, 0]) & (p <= ranges[:, 1]))
    path = data.groundtruth.position
    side = np.ptp(np.concatenate(drawn), axis=0).max()
    assert np.all(path[0] - ranges[:, 0] >= SCENE_MARGIN * side * 0.999)  # the start: inside
    length = ranges[:, 1] - ranges[:, 0]
    aspect = np.array([sc.aspectratio.x, sc.aspectratio.y, sc.aspectratio.z])
    np.testing.assert_allclose(aspect, length / length.max())  # one metre as long on each axis
    # the path's own trace is all there, broken at no gap (the synthetic poses have none)
    gt = next(t for t in fig.data if t.name.startswith("ground truth"))
    assert np.count_nonzero(np.isfinite(np.asarray(gt.x, dtype=float))) == len(path)
    # a flat site keeps some height; rows with a NaN are ignored
    r, a = scene_box(np.array([[0.0, 0, 0], [100, 20, 1], [np.nan, 1e6, 0]]))
    np.testing.assert_allclose(r[0], [-5, 105])
    assert a[0] == 1 and a[2] == pytest.approx((r[2, 1] - r[2, 0]) / 110) and a[2] > 0.1


def test_break_gaps_is_shared():
    """One helper breaks the lines at gaps: the 3D path, the figures, the evaluation's."""
    from rtsgt.report.figures import GAP_FACTOR, break_gaps

    t = np.array([0.0, 1, 2, 3, 10, 11, 12, 3 * GAP_FACTOR + 12.5])
    v = np.arange(t.size, dtype=float)
    b = break_gaps(t, np.column_stack([t, v]))
    assert b.shape == (t.size + 2, 2)
    assert np.flatnonzero(np.isnan(b[:, 1])).tolist() == [4, 8]
    np.testing.assert_array_equal(b[np.isfinite(b[:, 1]), 1], v)
    assert break_gaps(t, v, factor=100.0).shape == v.shape  # no step over 100 x 1 s


def test_evaluation_error_lines_break_at_gaps():
    """Issue 26: `rtsgt evaluate --plot` drew its lines across the gaps between the
    associated poses; each line (and band) now breaks at each of the two gaps."""
    import warnings

    from matplotlib.collections import PolyCollection

    from rtsgt.errors import RtsgtWarning
    from rtsgt.evaluation import evaluate
    from rtsgt.report.eval_plots import _error_figure, _top_view
    from rtsgt.types import PoseTrajectory

    rng = np.random.default_rng(3)
    t = np.arange(0, 60, 0.5)
    t = t[((t < 20) | (t >= 30)) & ((t < 42) | (t >= 47))]  # gaps of 10.5 and 5.5 s
    p = np.column_stack([5 * np.cos(t / 10), 5 * np.sin(t / 10), 0.1 * t])
    q = np.tile([0.0, 0, 0, 1], (t.size, 1))
    cov = np.broadcast_to(np.eye(6) * 1e-6, (t.size, 6, 6)).copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RtsgtWarning)  # RPE pairs that span the gaps
        r = evaluate(PoseTrajectory(t, p, q, cov),
                     PoseTrajectory(t, p + rng.normal(0, 2e-3, p.shape), q), align="se3")
    after = [int(np.searchsorted(t, 30.0)), int(np.searchsorted(t, 47.0))]
    breaks = [after[0], after[1] + 1]  # where the NaN rows are, one inserted before each
    fig, _, _ = _error_figure(r)
    lines = [ln for ax in fig.axes for ln in ax.lines]
    assert len(lines) == 4 + 3  # |error| with 3 sigma lines; x, y, z
    for ln in lines:
        x = np.asarray(ln.get_xdata(), dtype=float)
        y = np.asarray(ln.get_ydata(), dtype=float)
        assert x.size == t.size + 2
        assert np.flatnonzero(np.isnan(y)).tolist() == breaks, ln.get_label()
        assert np.flatnonzero(np.isnan(x)).tolist() == breaks
    for ax in fig.axes[1:]:  # each sigma band in three pieces
        bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
        assert [len(c.get_paths()) for c in bands] == [3, 3, 3]
    top, _, _ = _top_view(r, 10, None)
    for ln in top.axes[0].lines:
        assert np.flatnonzero(np.isnan(np.asarray(ln.get_xdata(), float))).tolist() == breaks


def test_report_without_plotly(data, analysis, monkeypatch):
    monkeypatch.setitem(sys.modules, "plotly", None)
    monkeypatch.setitem(sys.modules, "plotly.graph_objects", None)
    page, info = render_report(data, analysis, figures={}, figure_format="png")
    assert not info["view3d"]
    assert "id='no-view3d'" in page and "rtsgt[report]" in page


def test_ellipsoid_mesh_lies_on_the_ellipsoids():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(4, 3, 3))
    covs = A @ np.swapaxes(A, 1, 2) * 1e-6 + 1e-8 * np.eye(3)
    centres = rng.normal(size=(4, 3))
    verts, faces, which = ellipsoid_mesh(centres, covs, 50.0)
    d = verts - centres[which]
    m2 = np.einsum("vi,vij,vj->v", d, np.linalg.inv(covs)[which], d)
    np.testing.assert_allclose(m2, CHI2_3_95 * 50.0 ** 2, rtol=1e-9)
    assert faces.max() < verts.shape[0] and faces.shape[0] % 4 == 0
    # a closed surface: every edge is shared by exactly two triangles
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert np.all(counts == 2)


# --------------------------------------------------------------------------------------------
# HTML report in a real headless browser (Chromium, DevTools protocol over a pipe)
# --------------------------------------------------------------------------------------------


def _find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        exe = shutil.which(name)
        if exe:
            return exe
    return None


@pytest.fixture(scope="module")
def chromium() -> str:
    """A Chromium already on the machine; the tests never install one (``.ci/run`` does)."""
    exe = _find_chromium()
    if exe is None:
        pytest.skip("no Chromium on PATH (chromium, chromium-browser, google-chrome): the browser "
                    "test of the report needs one; .ci/run installs Debian's chromium")
    return exe


class DevTools:
    """A minimal Chrome DevTools Protocol client over ``--remote-debugging-pipe``.

    Chromium reads commands on fd 3 and writes replies and events on fd 4, one JSON message
    each, terminated by a NUL byte.
    """

    def __init__(self, exe: str, profile: Path):
        cmd_r, cmd_w = os.pipe()
        out_r, out_w = os.pipe()

        def child_fds():  # runs in the child between fork and exec
            os.dup2(cmd_r, 3)
            os.dup2(out_w, 4)

        args = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}",
                "--enable-unsafe-swiftshader", "--window-size=1280,900",
                "--remote-debugging-pipe", "about:blank"]
        self.proc = subprocess.Popen(args, preexec_fn=child_fds, pass_fds=(3, 4),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(out_w)
        self.w, self.r = cmd_w, out_r
        self.buf = b""
        self.n = 0
        self.events: list[dict] = []
        self.session: str | None = None

    def _read(self, timeout: float) -> dict:
        end = time.monotonic() + timeout
        while b"\0" not in self.buf:
            left = end - time.monotonic()
            if left <= 0:
                raise TimeoutError("no message from chromium")
            ready, _, _ = select.select([self.r], [], [], left)
            if ready:
                chunk = os.read(self.r, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed the DevTools pipe")
                self.buf += chunk
        msg, self.buf = self.buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method: str, params: dict | None = None, timeout: float = 60.0,
             browser: bool = False) -> dict:
        self.n += 1
        msg = {"id": self.n, "method": method, "params": params or {}}
        if self.session and not browser:
            msg["sessionId"] = self.session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        while True:
            reply = self._read(timeout)
            if reply.get("id") == self.n:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def evaluate(self, expression: str, timeout: float = 60.0):
        r = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                           "awaitPromise": True}, timeout)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, method: str, timeout: float = 60.0) -> dict:
        for e in self.events:
            if e.get("method") == method:
                return e
        end = time.monotonic() + timeout
        while True:
            e = self._read(max(0.01, end - time.monotonic()))
            self.events.append(e)
            if e.get("method") == method:
                return e

    def screenshot(self, path: Path, clip: dict) -> None:
        shot = self.send("Page.captureScreenshot", {"format": "png", "clip": {**clip, "scale": 1},
                                                    "captureBeyondViewport": True})
        path.write_bytes(base64.b64decode(shot["data"]))

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=10, browser=True)
        except Exception:  # noqa: BLE001 - best effort, the process is killed below
            pass
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        os.close(self.w)
        os.close(self.r)


def _console_errors(events: list[dict]) -> list[str]:
    errors = []
    for e in events:
        m, p = e.get("method"), e.get("params", {})
        if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            errors.append("console: " + " ".join(str(a.get("value", a.get("description")))
                                                 for a in p.get("args", [])))
        elif m == "Runtime.exceptionThrown":
            d = p["exceptionDetails"]
            errors.append("exception: " + str(d.get("exception", {}).get("description",
                                                                           d.get("text"))))
        elif m == "Log.entryAdded" and p["entry"]["level"] == "error":
            errors.append(f"log ({p['entry']['source']}): {p['entry']['text']}")
    return errors


def test_report_in_headless_chromium(chromium, data, analysis, tmp_path):
    from rtsgt.report.html import write_report_file

    info = write_report_file(data, analysis, tmp_path / "report.html")
    assert info.view3d
    browser = DevTools(chromium, tmp_path / "profile")
    try:
        target = browser.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        browser.session = browser.send("Target.attachToTarget",
                                       {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Runtime", "Log", "Page", "Network"):
            browser.send(f"{domain}.enable")
        browser.send("Emulation.setDeviceMetricsOverride",
                     {"width": 1280, "height": 900, "deviceScaleFactor": 1, "mobile": False})
        browser.send("Page.navigate", {"url": info.path.resolve().as_uri()})
        browser.wait_for("Page.loadEventFired", 90)
        rendered = None
        for _ in range(300):
            rendered = browser.evaluate(
                f"document.getElementById('{VIEW3D_ID}').getAttribute('data-rendered')")
            if rendered == "1":
                break
            time.sleep(0.1)
        assert rendered == "1", "the plotly 3D view did not finish drawing"
        n_canvas = browser.evaluate(f"document.querySelectorAll('#{VIEW3D_ID} .gl-container "
                                    "canvas').length")
        assert n_canvas >= 1, "no WebGL canvas in the 3D view"
        traces = browser.evaluate(f"document.getElementById('{VIEW3D_ID}')._fullData"
                                  ".map(t => t.type)")
        assert "mesh3d" in traces and "scatter3d" in traces
        n_vertices = browser.evaluate(f"document.getElementById('{VIEW3D_ID}')._fullData"
                                      ".filter(t => t.type == 'mesh3d')[0].x.length")
        assert n_vertices == info.n_ellipsoids * (2 + 7 * 12)
        assert browser.evaluate("document.querySelectorAll('figure img').length") == 4
        assert browser.evaluate("Array.from(document.querySelectorAll('figure img'))"
                                ".every(i => i.complete && i.naturalWidth > 0)")
        # the axes plotly draws are the report's (no autorange): the whole path is in the box
        scene = browser.evaluate(f"(() => {{const s = document.getElementById('{VIEW3D_ID}')"
                                 "._fullLayout.scene; return [s.xaxis.range, s.yaxis.range, "
                                 "s.zaxis.range, s.aspectratio];})()")
        ranges = np.array(scene[:3])
        path = data.groundtruth.position
        assert np.all((path >= ranges[:, 0]) & (path <= ranges[:, 1]))
        assert max(scene[3].values()) == pytest.approx(1.0)
        # rotate and zoom the view as a user would (camera change), then let it redraw
        assert browser.evaluate(
            f"Plotly.relayout(document.getElementById('{VIEW3D_ID}'), "
            "{'scene.camera.eye': {x: 0.9, y: -1.2, z: 0.7}}).then(() => 'ok')") == 'ok'
        box = browser.evaluate(
            f"(() => {{const e = document.getElementById('{VIEW3D_ID}'); e.scrollIntoView();"
            " const b = e.getBoundingClientRect();"
            " return {x: b.x + scrollX, y: b.y + scrollY, width: b.width, height: b.height};})()")
        time.sleep(1.0)
        SCREENSHOT_DIR.mkdir(parents=True, exist_ok=True)
        view_png = tmp_path / "report_view3d.png"
        browser.screenshot(view_png, box)
        size = browser.send("Page.getLayoutMetrics")["cssContentSize"]
        full_png = tmp_path / "report_full.png"
        browser.screenshot(full_png, {"x": 0, "y": 0, "width": size["width"],
                                      "height": size["height"]})
        events = list(browser.events)
    finally:
        browser.close()
    for p in (view_png, full_png):
        shutil.copy(p, SCREENSHOT_DIR / p.name)
    print(f"\nscreenshots: {SCREENSHOT_DIR / view_png.name} and {SCREENSHOT_DIR / full_png.name}")
    errors = _console_errors(events)
    assert errors == [], errors
    urls = [e["params"]["request"]["url"] for e in events
            if e.get("method") == "Network.requestWillBeSent"]
    assert urls and all(u.startswith(("file:", "data:", "blob:", "about:")) for u in urls), urls
    # the 3D view is drawn: the scene is not blank and shows the black path and the ellipsoids
    img = mpimg.imread(io.BytesIO(view_png.read_bytes()))[..., :3]
    assert img.shape[0] > 500 and img.shape[1] > 800
    non_white = np.mean(np.any(img < 0.9, axis=-1))
    assert non_white > 0.05, f"the 3D view looks blank ({non_white:.3f} non-white)"
    dark = np.mean(np.all(img < 0.15, axis=-1))
    assert dark > 1e-4, "no dark pixels: the ground-truth path is not drawn"
    assert len(np.unique((img * 16).astype(int).reshape(-1, 3), axis=0)) > 50
    full = mpimg.imread(io.BytesIO(full_png.read_bytes()))
    assert full.shape[0] > 3000  # tables, 4 figures, the 3D view, summary


#: A4's width less the report's page margins (``@page``: 11 mm each side), in CSS pixels.
A4_CONTENT_PX = int((210 - 2 * 11) / 25.4 * 96)


def test_real_report_prints_on_a4_in_chromium(chromium, real_run, tmp_path):
    """Issue 26: printed, the report is A4 and no table is wider than the page (the
    static-stretch table was 1068 px wide for 695 px of page); the 3D view, which does not
    print, gives way to a note; 8 pages for the real excerpt (21 before, half of them the
    flat dump of summary.json)."""
    out, r = real_run
    assert r.exit_code == 0, r.output
    browser = DevTools(chromium, tmp_path / "profile")
    try:
        target = browser.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        browser.session = browser.send("Target.attachToTarget",
                                       {"targetId": target, "flatten": True})["sessionId"]
        browser.send("Page.enable")
        browser.send("Emulation.setDeviceMetricsOverride",
                     {"width": A4_CONTENT_PX, "height": 1000, "deviceScaleFactor": 1,
                      "mobile": False})
        browser.send("Emulation.setEmulatedMedia", {"media": "print"})
        browser.send("Page.navigate", {"url": (out / "report.html").resolve().as_uri()})
        browser.wait_for("Page.loadEventFired", 90)
        layout = browser.evaluate(
            "(() => { const W = document.documentElement.clientWidth; return {W: W,"
            " scroll: document.documentElement.scrollWidth,"
            " tables: Array.from(document.querySelectorAll('table')).map(t => [t.id,"
            "  t.getBoundingClientRect().right, t.scrollWidth, t.clientWidth]),"
            f" view: getComputedStyle(document.getElementById('{VIEW3D_ID}')).display,"
            " note: (e => e && getComputedStyle(e).display)("
            "document.querySelector('#view .print-only'))};"
            "})()")
        pdf = base64.b64decode(browser.send("Page.printToPDF", {"preferCSSPageSize": True},
                                            timeout=120)["data"])
    finally:
        browser.close()
    assert layout["W"] <= A4_CONTENT_PX and layout["scroll"] <= layout["W"]
    assert len(layout["tables"]) > 15
    wide = [t for t in layout["tables"] if t[1] > layout["W"] + 0.5 or t[2] > t[3] + 1]
    assert wide == [], wide
    assert layout["view"] == "none" and layout["note"] == "block"
    boxes = {tuple(float(x) for x in m) for m in re.findall(
        rb"/MediaBox\s*\[\s*0\s+0\s+([\d.]+)\s+([\d.]+)\s*\]", pdf)}
    assert len(boxes) == 1
    w, h = boxes.pop()
    assert w == pytest.approx(595.3, abs=1.0) and h == pytest.approx(841.9, abs=1.0)  # A4, pt
    pages = len(re.findall(rb"/Type\s*/Page\b", pdf))
    assert 5 <= pages <= 10, pages
    (SCREENSHOT_DIR / "report_real_a4.pdf").parent.mkdir(parents=True, exist_ok=True)
    (SCREENSHOT_DIR / "report_real_a4.pdf").write_bytes(pdf)


# --------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------


@pytest.fixture()
def run_dir(data, tmp_path):
    return write_run_dir(data, tmp_path / "run")


def test_cli_analyze_prints_table_next_to_paper(run_dir):
    r = runner.invoke(app, ["analyze", str(run_dir)], env={"COLUMNS": "120"})
    assert r.exit_code == 0, r.output
    out = r.stdout
    assert "paper" in out and "0-75m" in out and ">150m" in out
    row = next(line for line in out.splitlines() if line.strip().startswith("calibration"))
    for v in ("1.32", "0.91", "1.88", "5.49"):
        assert v in row
    row = next(line for line in out.splitlines() if line.strip().startswith("instrument"))
    assert "2.1" in row and "2.78" in row
    for name in FIGURE_NAMES:
        assert (run_dir / "analysis" / f"{name}.png").is_file()
        assert (run_dir / "analysis" / f"{name}.svg").is_file()
    js = json.loads((run_dir / "analysis" / "analysis.json").read_text())
    assert js["bins"]["labels"] == ["0-75 m", "75-150 m", "> 150 m"]


def test_cli_analyze_json_bins_and_out(run_dir, tmp_path):
    r = runner.invoke(app, ["analyze", str(run_dir), "--json", "--bins", "0,100",
                            "--out", str(tmp_path / "figs"), "--formats", "png"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["bins"]["labels"] == ["0-100 m", "> 100 m"]
    assert sum(d["bins"]["counts"]) == d["n_measurements"]
    assert {s["source"] for s in d["sources"]} >= {"instrument", "calibration", "all"}
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == sorted(
        [f"{n}.png" for n in FIGURE_NAMES] + ["analysis.json", ".rtsgt-output.json"])


def test_cli_report_writes_html(run_dir):
    r = runner.invoke(app, ["report", str(run_dir), "--figure-format", "png"])
    assert r.exit_code == 0, r.output
    path = Path(r.stdout.strip())
    assert path == run_dir / "report.html" and path.stat().st_size > 3_000_000
    page = path.read_text()
    assert page.count("src='data:image/png;base64,") == 4


def test_cli_bad_input(run_dir, tmp_path):
    r = runner.invoke(app, ["analyze", str(tmp_path / "missing")])
    assert r.exit_code != 0 and r.stderr.startswith("error: ")
    assert "run directory not found" in r.stderr
    r = runner.invoke(app, ["analyze", str(run_dir), "--bins", "75,0"])
    assert r.stderr.startswith("error: ") and "increasing" in r.stderr
    r = runner.invoke(app, ["report", str(run_dir), "--figure-format", "gif"])
    assert r.exit_code == 2
    # through the console entry point: one line on stderr, exit code 1
    p = subprocess.run([sys.executable, "-c", "from rtsgt.cli.entry import main; main()",
                        "analyze", str(tmp_path / "missing")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 1 and p.stderr.startswith("error:") and "missing" in p.stderr


@pytest.mark.skipif(os.name != "posix", reason="the stand-in browser is a shell script")
def test_cli_report_open_prints_the_path_and_opens_it(run_dir, tmp_path):
    """``--open`` hands the report's file:// URI to the system browser (Python's webbrowser).

    The browser is the one the user chooses with the BROWSER environment variable, here a
    script that writes down what it was asked to open, so that no real browser starts.
    """
    seen = tmp_path / "browser-was-asked.txt"
    browser = tmp_path / "browser.sh"
    browser.write_text(f"#!/bin/sh\nprintf '%s' \"$1\" > '{seen}'\n")
    browser.chmod(0o755)
    p = subprocess.run([sys.executable, "-c", "from rtsgt.cli.entry import main; main()",
                        "report", str(run_dir), "--open", "--figure-format", "png"],
                       capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, BROWSER=str(browser)))
    assert p.returncode == 0, p.stderr
    path = Path(p.stdout.strip())
    assert path == run_dir / "report.html" and path.is_file()
    assert seen.read_text() == path.resolve().as_uri()
    assert "could not start a browser" not in p.stderr


def test_cli_demo_writes_the_report_and_says_where(tmp_path):
    r = runner.invoke(app, ["demo", "--out", str(tmp_path / "demo"), "--duration", "60",
                            "--engine", "linear"], env={"COLUMNS": "120"})
    assert r.exit_code == 0, r.output
    line = next(x for x in r.stdout.splitlines() if x.startswith("report: "))
    path = Path(line.removeprefix("report: "))
    assert path == (tmp_path / "demo" / "run" / "report.html").resolve() and path.is_file()
    page = path.read_text()
    assert "id='sources-table'" in page and page.count("<img alt=") == 4


@pytest.fixture(scope="module")
def real_run(tmp_path_factory):
    """`rtsgt run --report` on the real excerpt: the run directory and the command's result."""
    out = tmp_path_factory.mktemp("real") / "real"
    r = runner.invoke(app, ["run", str(EXAMPLE), "--out", str(out), "--report",
                            "--engine", "linear"], env={"COLUMNS": "120"})
    return out, r


def test_real_excerpt_run_report_and_analyze(real_run):
    """`rtsgt run --report` then `rtsgt analyze` on the real excerpt
    (docs/paper-figures.md#the-real-excerpt)."""
    out, r = real_run
    assert r.exit_code == 0, r.output
    assert f"report: {out.resolve() / 'report.html'}" in r.stderr
    assert (out / "report.html").stat().st_size > 3_000_000
    r = runner.invoke(app, ["analyze", str(out)], env={"COLUMNS": "120"})
    assert r.exit_code == 0, r.output
    rows: dict[str, str] = {}
    for line in r.stdout.splitlines():  # the first table: the prisms, next to the paper
        if line.strip():
            rows.setdefault(line.split()[0], line)
    for v in ("1.32", "0.91", "1.88", "5.49"):  # the paper's, next to ours
        assert v in rows["calibration"]
    assert "2.1" in rows["instrument"] and "2.78" in rows["instrument"]
    assert "0-75m" in r.stdout and "75-150m" in r.stdout and ">150m" in r.stdout
    js = json.loads((out / "analysis" / "analysis.json").read_text())
    med = {row["source"]: row for row in js["sources"]}
    # the excerpt's measurements are all within 150 m of the stations
    assert js["bins"]["counts"][2] == 0 and sum(js["bins"]["counts"]) == js["n_measurements"]
    # the instrument source is set by the datasheet (4 mm + 2 ppm, 2"): the paper's 2.1 mm;
    # the calibration (same GCPs as the paper's deployment) near its 0.91 mm below 75 m
    assert med["instrument"]["median_mm"] == pytest.approx(2.1, rel=0.1)
    assert med["calibration"]["bins"][0]["median_mm"] == pytest.approx(0.91, rel=0.35)
    for s in ("tilt", "atmosphere"):  # both well under a millimetre, as in the paper
        assert med[s]["median_mm"] < 0.3
    data = read_run(out)
    assert len(data.gcp_names) == 12 and len(data.stations) == 3


def test_real_excerpt_report_static_table_and_run_section(real_run):
    """Issue 26: the static-stretch table at A4 (7 columns, a group row per prism, units in
    the headers, 12 columns before); the run's section from its summary.json."""
    out, r = real_run
    assert r.exit_code == 0, r.output
    page = (out / "report.html").read_text(encoding="utf-8")
    summary = json.loads((out / "summary.json").read_text())
    static = _element(page, "<table id='check-static'>")
    rows = re.findall(r"<tr\b[^>]*>(.*?)</tr>", static)
    head, body = rows[0], rows[1:]
    assert len(re.findall(r"<th\b", head)) == 7
    assert "scatter / predicted (mm)" in head and "correlation time (s)" in head
    prisms = summary["self_checks"]["static_noise"]["prisms"]
    groups = [x for x in body if "colspan='7'" in x]
    assert len(groups) == len(prisms) == 3
    for pid, e in prisms.items():
        assert any(f"prism {pid} <small>(station {e['station']}, {e['samples']} samples)"
                   in g for g in groups)
    for x in body:
        if "colspan" not in x:
            assert len(re.findall(r"<td\b", x)) == 7
    assert static.count("<td class='verdict'>") == 2 * 3 * len(prisms)
    # the run's section: each option, each stage's time, each warning; the file is linked
    assert "<section id=\"summary\">" not in page and "qc_fit.motion_prior" not in page
    run = _element(page, "<section id=\"run\">", "</section>")
    assert "<a href='summary.json'>summary.json</a>" in run
    options = _element(run, "<table id='run-options'")
    assert options.count("<tr>") == len(summary["parameters"])
    timings = _element(run, "<table id='run-timings'")
    for stage in summary["timings_s"]:
        assert f"<th>{stage.replace('_', ' ')}</th>" in timings
    assert run.count("<li>") == len(summary["warnings"]) > 0
    levelling = _element(page, "<table id='check-levelling'>")
    assert levelling.count("<td class='verdict'>levelled</td>") == 2  # stations 2 and 3
