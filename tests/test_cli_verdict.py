"""What a user reads at the end: one verdict line, grouped warnings, tables that never cut.

The run's verdict (:mod:`rtsgt.checks.verdict`) on self-check results with a known answer; the
tables of :mod:`rtsgt.cli.tables` at every console width; the terminal output of ``rtsgt run``
on the real excerpt and of ``rtsgt evaluate`` redirected to a file (80 columns), as a user's
shell gives it; the demo's verdict by the split test
(docs/self-checks.md#the-runs-verdict).
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from rich.console import Console

from _paths import EXAMPLE_TOML
from rtsgt.checks.verdict import SHOWN_REASONS, run_verdict
from rtsgt.cli.common import warning_groups
from rtsgt.cli.tables import TextTable

ENTRY = "from rtsgt.cli.entry import main; main()"


def _ratio(value, lo, hi, verdict, **extra):
    return {"interval_95": [lo, hi], "verdict": verdict, **extra}


def _checks(overall="consistent", regime="consistent", clock="consistent", block="consistent"):
    """Self-check results shaped as a run writes them, with chosen verdicts."""
    return {
        "inter_prism_distances": {
            "overall": _ratio(1, 0.5, 1.6, overall, mean_z2=3.08 if overall == "optimistic"
                              else 1.0, poses=6659),
            "regimes": {"cruising": _ratio(1, 0.5, 1.7, regime, mean_z2=4.52, poses=300)}},
        "block_cv": {"overall": _ratio(1, 0.9, 1.1, block, nees_per_dof=0.75, blocks=158)},
        "inter_prism_structure": {"clock": {"verdict": clock, "chi2_per_dof": 33.0,
                                            "critical": 1.9},
                                  "prism_orientation": {"verdict": "consistent", "f": 1.0,
                                                        "critical": 2.0}},
    }


def test_verdict_levels_follow_the_worst_finding():
    ok = run_verdict(_checks(), kept=100, queried=100)
    assert ok.level == "usable" and ok.usable and ok.findings == ()
    assert ok.line("x/summary.json") == "verdict: usable; details in x/summary.json"
    # a covariance too large is a note, not a caveat
    note = run_verdict(_checks(block="pessimistic"), kept=100, queried=100)
    assert note.level == "usable" and [f.severity for f in note.findings] == [0]
    caveat = run_verdict(_checks(regime="optimistic"), kept=100, queried=100)
    assert caveat.level == "usable, with caveats" and caveat.usable
    assert "cruising (z^2 4.52 > 1.70)" in caveat.line()
    # the whole hour of 2022-11-10: z^2 3.08 over the run, the clocks drifting (chi2/dof 33)
    hour = run_verdict(_checks(overall="optimistic", regime="optimistic", clock="optimistic"),
                       kept=6659, queried=6659)
    assert hour.level == "not usable as is" and not hour.usable
    assert [f.check for f in hour.reasons] == ["inter-prism distances", "clock offsets"]
    line = hour.line("run/summary.json")
    assert "inter-prism z^2 3.08" in line and "chi2/dof 33.00 above 1.90" in line
    assert "cruising" not in line  # a caveat is not among the reasons of a worse level
    assert line.endswith("; 1 more in run/summary.json")
    assert len(hour.reasons[:SHOWN_REASONS]) == 2


def test_verdict_of_no_pose_and_of_a_prism_off_its_survey():
    none = run_verdict({}, kept=0, queried=480)
    assert none.level == "not usable as is" and "0 of 480" in none.line()
    # 2022-11-09: the tracked distance of prisms 1-3 is 27.5 mm shorter than the survey
    survey = {"1-3": {"median_deviation_mm": -27.5, "ratio": -6.2},
              "1-2": {"median_deviation_mm": 0.9, "ratio": 0.3}}
    moved = run_verdict({}, kept=100, queried=100, distance_check=survey)
    assert moved.level == "not usable as is"
    assert "1-3 -27.5 mm (-6.2 sigma)" in moved.line() and "1-2" not in moved.line()
    few = run_verdict({}, kept=40, queried=100)
    assert few.level == "usable, with caveats" and "40 of 100" in few.line()


def test_a_prism_the_joint_engine_found_moved_is_a_caveat_with_its_size():
    prisms = {"1": {"moved": False, "shift_mm": [0.1, 0.0, 0.0], "largest_sigma_mm": 0.4},
              "2": {"moved": True, "shift_mm": [6.0, 8.0, 0.0], "largest_sigma_mm": 11.27}}
    v = run_verdict({}, kept=100, queried=100, joint={"prisms": prisms})
    assert v.level == "usable, with caveats" and len(v.findings) == 1, v.findings
    assert "prism 2 moved 10.0 mm" in v.line() and "11.3 mm" in v.line(), v.line()
    assert run_verdict({}, kept=100, queried=100, joint={"prisms": None}).level == "usable"
    del prisms["2"]["largest_sigma_mm"]  # a run written before the field was
    v = run_verdict({}, kept=100, queried=100, joint={"prisms": prisms})
    assert "prism 2 moved 10.0 mm" in v.line() and "sigma up to" not in v.line(), v.line()


def test_undecided_prism_hypotheses_are_a_caveat_naming_the_prisms():
    """Where the joint engine carries several prisms' hypotheses
    (docs/joint.md#which-prism-moved) the verdict names them and their weight; a move found
    alone does not."""
    prisms = {"1": {"moved": False, "moved_weight": 0.5, "shift_mm": [0.1, 0.0, 0.0]},
              "2": {"moved": True, "moved_weight": 0.5, "shift_mm": [6.0, 8.0, 0.0]},
              "3": {"moved": False, "moved_weight": 0.0, "shift_mm": [0.0, 0.1, 0.0]}}
    v = run_verdict({}, kept=100, queried=100, joint={"prisms": prisms})
    (f,) = [f for f in v.findings if f.check == "which prism moved"]
    assert f.severity == 1 and "prisms 1 and 2 each carried at weight 0.50" in f.text, f.text
    prisms["1"]["moved_weight"], prisms["2"]["moved_weight"] = 0.0, 1.0
    v = run_verdict({}, kept=100, queried=100, joint={"prisms": prisms})
    assert [f.check for f in v.findings] == ["moved prism"], v.findings


def test_a_move_no_station_sees_is_a_note_with_the_poses_turn_per_mm():
    """Three prisms share their blind direction (their plane's normal): the note names it
    and the range of the poses' turn per mm; it leaves the level as it was; two prisms'
    several directions are left to summary.json; a rig without one has no note
    (docs/joint.md#what-no-station-sees)."""
    n = [0.22904714, -0.21176024, 0.95010263]
    turns = {"1": 1.58, "2": 1.40, "3": 1.14}
    prisms = {k: {"moved": False, "shift_mm": [0.0, 0.0, 0.0], "blind_directions": [n],
                  "blind_turn_mrad_per_mm": [t]} for k, t in turns.items()}
    v = run_verdict({}, kept=100, queried=100, joint={"prisms": prisms})
    assert v.level == "usable" and [(f.severity, f.check) for f in v.findings] == [
        (0, "what no station sees")], v.findings
    text = v.findings[0].text
    assert "prisms 1, 2 and 3 across their plane, along (0.23, -0.21, 0.95)" in text, text
    assert "each mm of it turns every pose by 1.1-1.6 mrad, and the poses take the survey" in text
    v = run_verdict({}, kept=100, queried=100,
                    joint={"prisms": prisms, "prism_stability_mm": 2.0})
    assert "the poses carry a move of 2 mm (1 sigma) there" in v.findings[0].text, v.findings
    two = {k: {"blind_directions": [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
               "blind_turn_mrad_per_mm": [2.5, 2.5]} for k in "12"}
    (f,) = run_verdict({}, kept=100, queried=100, joint={"prisms": two}).findings
    assert "in the directions summary.json gives" in f.text and "by 2.5 mrad," in f.text, f.text
    for p in prisms.values():  # four prisms off one plane: none
        p["blind_directions"], p["blind_turn_mrad_per_mm"] = [], []
    assert not run_verdict({}, kept=100, queried=100, joint={"prisms": prisms}).findings


def test_static_correlation_is_a_caveat_only_where_the_gps_do_not_carry_it():
    comp = {"level": {"verdict": "consistent"},
            "correlation": {"verdict": "optimistic", "correlation_time_s": 2.5}}
    static = {"prisms": {"1": {c: comp for c in ("range", "horizontal", "vertical")}}}
    ignored = run_verdict({"static_noise": static}, kept=10, queried=10)
    assert ignored.level == "usable, with caveats" and "correlated over 2.5 s" in ignored.line()
    carried = {"prisms": {"1": {c: {"applied": True} for c in ("range", "horizontal",
                                                               "vertical")}}}
    inflated = run_verdict({"static_noise": static}, kept=10, queried=10,
                           correlated_noise=carried)
    assert inflated.level == "usable"


@pytest.mark.parametrize("width", [20, 40, 60, 80, 100, 160])
def test_tables_never_cut_a_word_or_a_number(width):
    t = TextTable("APE and NEES of a long trajectory", ("metric", "rmse", "mean", "verdict"))
    t.add_row("APE translation (mm), all pairs", "8716.543", "-12345.678901",
              "[green]inconsistent[/green] (autocorrelation)")
    t.add_section()
    t.add_row("relative position", "0.000123456", "4.5e-07", "consistent (split)")
    buf = io.StringIO()
    t.print(Console(file=buf, width=width, force_terminal=False, color_system=None))
    text = buf.getvalue()
    assert "…" not in text
    words = set(text.split())
    for row in t.rows:
        for cell in row:
            for word in re.sub(r"\[/?green\]", "", cell).split():
                assert word in words or any(word in w for w in words), (width, word)
    if width >= 80:  # wide enough: a table
        assert "┃" in text or "│" in text
    if width == 40:  # too narrow for four columns: key-value lines
        assert "mean: -12345.678901" in text


def test_warnings_are_grouped_by_check():
    messages = [
        "self-check, static stretches: prism 1 (station 1, 51 samples): range level "
        "pessimistic; range correlation optimistic",
        "self-check, static stretches: prism 2 (station 2, 50 samples): range level pessimistic",
        "self-check, GCP fit of station 2: variance factor 27.54 outside [0.56, 1.57]",
        "self-check, GCP fit of station 3: variance factor 85.03 outside [0.56, 1.57]",
        "weather.csv: the weather record covers 80 % of the measurements; " + "x" * 200,
        "weather b.csv: 440 of 440 measurement times lie far (records 08:00 to 12:00 UTC; "
        "measurements 15:00 to 15:01 UTC, up to 3.0 h after the last record): " + "y" * 100,
    ]
    groups = warning_groups(messages)
    assert groups[0] == ("self-check, static stretches", ["prism 1", "prism 2"])
    assert groups[1] == ("self-check, GCP fit", ["station 2", "station 3"])
    assert groups[2] == ("weather.csv: the weather record covers 80 % of the measurements", [])
    assert groups[3] == (messages[-1], [])  # no clause ends outside the parentheses: whole


@pytest.fixture(scope="module")
def excerpt(tmp_path_factory):
    """``rtsgt run`` of the shipped excerpt through the console entry point, stdout and stderr
    redirected to files as a shell does (80 columns), once in full and once with ``-q``."""
    tmp = tmp_path_factory.mktemp("excerpt")
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    out = {}
    for name, extra in (("full", []), ("quiet", ["-q"])):
        p = subprocess.run([sys.executable, "-c", ENTRY, "run", str(EXAMPLE_TOML), "-o",
                            str(tmp / name), "--engine", "linear", *extra],
                           capture_output=True, text=True, timeout=600, env=env)
        assert p.returncode == 0, p.stderr
        out[name] = (p.stdout, p.stderr, tmp / name)
    return out


def test_run_ends_with_one_verdict_line(excerpt):
    stdout, stderr, run = excerpt["full"]
    assert "…" not in stdout and "…" not in stderr
    last = stdout.rstrip("\n").splitlines()[-1]
    summary = json.loads((run / "summary.json").read_text())
    verdict = summary["verdict"]
    # the excerpt: usable, with the static stretches' correlated noise as the first reason
    assert verdict["level"] == "usable, with caveats" and verdict["usable"]
    assert last.startswith("verdict: usable, with caveats: static noise correlated over")
    assert last.endswith(f"in {run / 'summary.json'}")
    # warnings: one line per check in the terminal, whole in summary.json
    shown = [ln for ln in stderr.splitlines() if ln.startswith("warning: ")]
    assert len(shown) == 4 < len(summary["warnings"]) == 9
    assert ("warning: self-check, static stretches (3 warnings: prism 1, prism 2, prism 3)"
            in shown)
    assert f"(the whole text of 9 warnings: {run / 'summary.json'})" in stderr
    assert any(ln.startswith("warning: self-check, static relative poses over 1 s: NEES / dof")
               for ln in shown)
    assert max(len(ln) for ln in shown) < 120
    # -q: the verdict line alone
    q_out, q_err, q_run = excerpt["quiet"]
    assert q_err == ""
    assert q_out.splitlines() == [last.replace(str(run), str(q_run))]


def test_evaluate_redirected_to_a_file_cuts_nothing(excerpt, tmp_path):
    """``rtsgt evaluate RUN EST > out.txt``: 80 columns, every number whole, and the verdict
    column says which test decided."""
    _, _, run = excerpt["full"]
    tum = np.loadtxt(run / "groundtruth.tum")
    tum[:, 1] += 12345.678  # an estimate far away: long numbers in every column
    est = tmp_path / "est.tum"
    np.savetxt(est, tum, fmt="%.9f")
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    with open(tmp_path / "out.txt", "w") as f:
        p = subprocess.run([sys.executable, "-c", ENTRY, "evaluate", str(run), str(est),
                            "--align", "none"], stdout=f, stderr=subprocess.PIPE, text=True,
                           timeout=300, env=env)
    assert p.returncode == 0, p.stderr
    text = (tmp_path / "out.txt").read_text()
    assert "…" not in text
    assert "12345678." in text  # the APE in mm, whole
    assert re.search(r"inconsistent \(split\)", text)
    assert max(len(ln) for ln in text.splitlines()) <= 80
