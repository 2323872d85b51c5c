"""The figures the README and docs/ quote cannot go stale.

A quoted figure is a number followed, without a space, by a marker naming it,
``2.51<!-- fig:excerpt.median_sigma_t_mm -->``; ``benchmarks/readme_figures.py`` writes the
figures of the real excerpt, the demo and the worked mounting example to ``docs/figures.json``
(docs/benchmarks.md#figures-of-the-readme-and-the-docs). Here:

- every marked number is the JSON's value at the precision printed (every group);
- the JSON's ``excerpt`` figures are those a run of the excerpt gives now (one run with the
  defaults through the script's own function, about 10 s), and so is every number quoted from
  them. The ``demo`` (a 600 s simulation) and ``mounting`` figures are not recomputed here.
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

from _paths import REPO

FIGURES = REPO / "docs" / "figures.json"
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
MARKER = re.compile(r"<!-- fig:([a-z]+)\.([a-z0-9_]+) -->")
NUMBER = re.compile(r"\d+(?:\.\d+)?$")


def _script():
    spec = importlib.util.spec_from_file_location(
        "readme_figures", REPO / "benchmarks" / "readme_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def quoted_figures(text: str) -> list[tuple[int, str, str, str | None]]:
    """(line, group, name, the number printed before the marker or None) of each marker."""
    out = []
    for m in MARKER.finditer(text):
        before = text[:m.start()]
        n = NUMBER.search(before)
        printed = None
        if n:
            printed = n[0]
            i = n.start()
            # a minus sign, not a dash between two numbers ("0.29<!-- ... -->-2.15")
            if i >= 1 and before[i - 1] == "-" and (i == 1 or before[i - 2] in " \t\n(,|"):
                printed = "-" + printed
        out.append((text.count("\n", 0, m.start()) + 1, m[1], m[2], printed))
    return out


def as_printed(value: float, printed: str) -> str:
    """``value`` with the decimals of ``printed``."""
    decimals = len(printed.split(".")[1]) if "." in printed else 0
    return f"{value:.{decimals}f}"


def _quotes():
    for page in PAGES:
        for line, group, name, printed in quoted_figures(page.read_text(encoding="utf-8")):
            yield f"{page.relative_to(REPO)}:{line}", group, name, printed


@pytest.fixture(scope="module")
def figures():
    return json.loads(FIGURES.read_text(encoding="utf-8"))


def test_the_marker_reading():
    text = "a (0.4001<!-- fig:m.x -->, -0.0001<!-- fig:m.y -->) and 0.29<!-- fig:e.lo -->-2.15" \
           "<!-- fig:e.hi --> m\nx <!-- fig:e.z -->"
    assert [q[3] for q in quoted_figures(text)] == ["0.4001", "-0.0001", "0.29", "2.15", None]
    assert quoted_figures(text)[-1][0] == 2
    assert as_printed(2.5073, "2.51") == "2.51" and as_printed(8716.52, "8717") == "8717"
    assert as_printed(-7.9e-05, "-0.0001") == "-0.0001"


def test_the_readme_quotes_its_main_figures():
    names = {f"{g}.{n}" for where, g, n, _ in _quotes() if where.startswith("README.md")}
    assert {"excerpt.median_sigma_t_mm", "excerpt.median_sigma_r_mrad", "excerpt.poses_kept",
            "excerpt.z2_overall", "demo.position_rmse_mm", "demo.median_sigma_t_mm",
            "demo.wall_s"} <= names


def test_every_quoted_figure_is_the_json_one(figures):
    wrong = []
    for where, group, name, printed in _quotes():
        if printed is None:
            wrong.append(f"{where}: the marker fig:{group}.{name} follows no number")
        elif name not in figures.get(group, {}):
            wrong.append(f"{where}: {group}.{name} is not in docs/figures.json")
        elif as_printed(figures[group][name], printed) != printed:
            wrong.append(f"{where}: {printed} printed, docs/figures.json has "
                         f"{as_printed(figures[group][name], printed)} ({group}.{name})")
    assert not wrong, "\n".join(wrong)


def test_the_excerpt_figures_are_current(figures):
    """A run of the excerpt gives the JSON's figures (to 0.2 %), and every number quoted from
    them at the precision printed; run ``python benchmarks/readme_figures.py --only excerpt``
    after a change that moves them."""
    now = _script().excerpt_figures()
    stored = figures["excerpt"]
    assert set(now) == set(stored)
    moved = [f"{k}: {stored[k]!r} in docs/figures.json, {now[k]!r} now" for k in sorted(now)
             if not np.isclose(now[k], stored[k], rtol=2e-3, atol=1e-9)]
    assert not moved, "\n".join(moved)
    stale = [f"{where}: {printed} printed, {as_printed(now[name], printed)} now ({name})"
             for where, group, name, printed in _quotes()
             if group == "excerpt" and printed is not None and name in now
             and as_printed(now[name], printed) != printed]
    assert not stale, "\n".join(stale)


def test_a_stale_quote_is_found(figures, tmp_path):
    """The check above fails on a number that no longer matches (the README's stale 2.9 mm)."""
    page = "median pose uncertainty 2.9<!-- fig:excerpt.median_sigma_t_mm --> mm"
    [(_, group, name, printed)] = quoted_figures(page)
    assert as_printed(figures[group][name], printed) != printed


def test_the_script_writes_every_group_it_is_asked_for(tmp_path, monkeypatch):
    """``--only`` keeps the groups not asked for; the JSON the script writes is what the tests
    read (a group computed by a stand-in, so that no run is needed here)."""
    script = _script()
    out = tmp_path / "figures.json"
    out.write_text(json.dumps({"demo": {"wall_s": 1.0}}))
    monkeypatch.setattr(script, "excerpt_figures", lambda: {"poses_kept": 3})
    script.main(["--only", "excerpt", "--out", str(out)])
    written = json.loads(out.read_text())
    assert written["demo"] == {"wall_s": 1.0} and written["excerpt"] == {"poses_kept": 3}
    assert Path(script.FIGURES_JSON) == FIGURES
