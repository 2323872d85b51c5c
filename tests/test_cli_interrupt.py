"""Ctrl-C at any moment: one line ``error: interrupted``, exit status 130, nothing half-written.

Real processes of the console entry point (:mod:`rtsgt.cli.entry`) get a real SIGINT: while
the command line starts (the imports of :mod:`rtsgt.cli.main`, which used to print a
traceback), and while ``rtsgt run`` processes a simulated deployment (where typer used to turn
the interrupt into exit status 130 without a word).
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rtsgt import __version__
from rtsgt.cli.main import app
from rtsgt.io.config import tomllib

ENTRY = "from rtsgt.cli.entry import main; main()"
#: A line of the progress display: a finished stage and its time.
PROGRESS = re.compile(r"^  \S.*: \d+\.\d\d s$")
ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not Path("/proc/self/maps").exists(),
                                reason="needs Linux's /proc to see where the process is")


def start(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", ENTRY, *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_numpy(p: subprocess.Popen, timeout: float = 60.0) -> None:
    """Until the process has loaded numpy's core (the imports of rtsgt.cli.main, past the
    entry point's first lines); fails if it ended first."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert p.poll() is None, p.communicate()
        if "_multiarray_umath" in Path(f"/proc/{p.pid}/maps").read_text():
            return
        time.sleep(0.002)
    raise AssertionError("numpy not loaded")


def finish(p: subprocess.Popen) -> tuple[str, str]:
    out, err = p.communicate(timeout=120)
    assert p.returncode == 130, (p.returncode, err)
    assert "Traceback" not in err and out == "", (out, err)
    return out, err


def test_an_interrupt_while_the_command_line_starts_is_one_line(tmp_path):
    out = tmp_path / "sim"
    p = start("simulate", out, "--duration", 30)
    wait_for_numpy(p)
    p.send_signal(signal.SIGINT)
    _, err = finish(p)
    assert err == "error: interrupted\n"
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def deployment(tmp_path_factory) -> Path:
    """A short simulated deployment whose run warns of nothing before its self-checks."""
    folder = tmp_path_factory.mktemp("sim") / "dep"
    r = CliRunner().invoke(app, ["simulate", str(folder), "--duration", "60", "--seed", "3"])
    assert r.exit_code == 0, r.output
    return folder


def test_an_interrupt_during_a_run_is_one_line_and_leaves_nothing(deployment, tmp_path):
    out = tmp_path / "run"
    p = start("run", deployment, "-o", out, "--engine", "linear")
    first = p.stderr.readline()  # the first stage done: the pipeline is at work
    assert PROGRESS.match(first.rstrip("\n")), first
    time.sleep(0.3)  # into the GP interpolation, seconds long
    p.send_signal(signal.SIGINT)
    _, err = finish(p)
    said = [ln for ln in err.splitlines() if not PROGRESS.match(ln)]
    assert said == ["error: interrupted"], err
    assert list(tmp_path.iterdir()) == []  # no run directory, no temporary one


def test_the_console_script_is_the_entry_point_and_answers_the_version():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"rtsgt": "rtsgt.cli.entry:main"}
    p = subprocess.run([sys.executable, "-c", ENTRY, "--version"], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0 and p.stderr == ""
    assert p.stdout == CliRunner().invoke(app, ["--version"]).stdout == f"rtsgt {__version__}\n"
