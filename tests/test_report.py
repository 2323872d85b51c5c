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


def test_report_summary_tables_are_escaped(data, analysis):
    from dataclasses import replace

    d = replace(data, summary={"deployment": "<script>alert(1)</script>",
                               "parameters": {"engine": "linear", "samples": 1000},
                               "calibration": {"residuals": [{"marker": "3", "mm": 1.5},
                                                             {"marker": "4", "mm": 2.5}]}})
    page, _ = render_report(d, analysis, figures={})
    assert "<script>alert(1)</script>" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "<td class='k'>engine</td>" in page
    assert "residuals (2 rows)" in page


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
    p = subprocess.run([sys.executable, "-c", "from rtsgt.cli.main import main; main()",
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
    p = subprocess.run([sys.executable, "-c", "from rtsgt.cli.main import main; main()",
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
                            "--engine", "linear", "--quiet"], env={"COLUMNS": "120"})
    assert r.exit_code == 0, r.output
    line = next(x for x in r.stdout.splitlines() if x.startswith("report: "))
    path = Path(line.removeprefix("report: "))
    assert path == (tmp_path / "demo" / "run" / "report.html").resolve() and path.is_file()
    page = path.read_text()
    assert "id='sources-table'" in page and page.count("<img alt=") == 4


def test_real_excerpt_run_report_and_analyze(tmp_path):
    """`rtsgt run --report` then `rtsgt analyze` on the real excerpt
    (docs/paper-figures.md#the-real-excerpt)."""
    out = tmp_path / "real"
    r = runner.invoke(app, ["run", str(EXAMPLE), "--out", str(out), "--report",
                            "--engine", "linear"], env={"COLUMNS": "120"})
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
