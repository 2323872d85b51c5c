"""Every command's ``--help`` in one style (:mod:`rtsgt.cli.main`).

Walks the commands of the application (click's introspection of ``rtsgt.cli.main.app``) and
reads each help text as a user sees it: values as upper-case words (``CONFIG``, ``PATH``,
``INTEGER``), never typer's ``{config}``, ``<path>`` or ``<list[Path]>``; every ``--out``
with its ``-o``; the figure formats under one name, ``--figure-format``, the old
``--formats`` of ``analyze`` kept working but hidden.
"""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from rtsgt.cli.main import app

runner = CliRunner()
GROUP = typer.main.get_command(app)
COMMANDS = sorted(GROUP.commands)
#: A value's word: upper case, digits and underscores, "..." for several.
WORD = re.compile(r"^[A-Z][A-Z0-9_]*(\.\.\.)?$")
#: typer's own style of a type, e.g. <path>, <int range>, <list[Path]>.
TYPER_TYPE = re.compile(r"<(?:path|str|int|float|bool|list|tuple|datetime|file|text)\b[^>]*>",
                        re.IGNORECASE)


def help_text(name: str) -> str:
    r = runner.invoke(app, [name, "--help"], env={"COLUMNS": "100"})
    assert r.exit_code == 0, r.output
    return r.output


def visible_options(name: str) -> list:
    return [p for p in GROUP.commands[name].params
            if p.param_type_name == "option" and not p.hidden]


def test_every_command_is_walked():
    assert {"init", "calibrate", "interpolate", "simulate", "run", "batch", "demo",
            "evaluate", "analyze", "report", "plan"} <= set(COMMANDS)


@pytest.mark.parametrize("name", COMMANDS)
def test_values_are_upper_case_words(name):
    text = help_text(name)
    assert "{" not in text and "}" not in text, text
    assert not TYPER_TYPE.search(text), TYPER_TYPE.search(text)[0]
    usage = text.splitlines()[0]
    assert re.fullmatch(rf"Usage: rtsgt {name} \[OPTIONS\]( \[?[A-Z][A-Z0-9_]*(\.\.\.)?\]?)*",
                        usage), usage
    for p in GROUP.commands[name].params:
        if p.param_type_name == "argument":
            assert WORD.match(p.metavar) and re.search(rf"^  {re.escape(p.metavar)}(\.\.\.)?  ",
                                                       text, re.M), (name, p.name)
        elif not (p.is_flag or p.count or p.hidden):
            assert WORD.match(p.metavar), (name, p.opts, p.metavar)
            # e.g. "-o, --out PATH", "--max-gap, --max-dt NUMBER"
            shown = re.findall(rf"((?:-[-\w]+, )*-[-\w]+) {re.escape(p.metavar)}\b", text)
            assert any(set(p.opts) <= set(m.split(", ")) for m in shown), (name, p.opts)


@pytest.mark.parametrize("name", COMMANDS)
def test_every_out_has_its_short_form(name):
    for p in visible_options(name):
        if "--out" in p.opts:
            assert "-o" in p.opts, (name, p.opts)


def test_figure_formats_have_one_name():
    """analyze wrote --formats and report --figure-format for the same thing."""
    named = {name: [p for p in visible_options(name)
                    if re.search(r"\bformats?\b", p.help or "", re.I)
                    and re.search(r"\bfigures?\b", p.help or "", re.I)]
             for name in COMMANDS}
    assert {n for n, ps in named.items() if ps} >= {"analyze", "report"}
    for name, ps in named.items():
        for p in ps:
            assert p.opts == ["--figure-format"], (name, p.opts)
    for name in COMMANDS:
        assert "--formats" not in help_text(name)


def test_the_old_spelling_still_works_and_both_are_refused(tmp_path):
    r = runner.invoke(app, ["analyze", str(tmp_path), "--formats", "gif"])
    assert r.exit_code == 2 and "--formats" in r.stderr and "gif" in r.stderr
    r = runner.invoke(app, ["analyze", str(tmp_path), "--formats", "png", "--figure-format",
                            "svg"])
    assert r.exit_code == 2 and "--figure-format only" in r.stderr
