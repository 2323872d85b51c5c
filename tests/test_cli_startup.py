"""The command line starts at once: its help imports nothing heavy (:mod:`rtsgt.cli.main`).

``rtsgt --help`` and every ``rtsgt <command> --help`` are rendered in a fresh Python process,
which then lists the heavy modules it imported: none may be (numpy, scipy, matplotlib, Dask,
and rtsgt's numeric core, pipeline, reports). ``rtsgt run`` without ``--report`` draws no
figure and so never imports matplotlib. No timings: what is imported decides start-up time.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

#: Third-party modules the command line's help must not import.
HEAVY_PACKAGES = ("numpy", "scipy", "matplotlib", "dask", "distributed")
#: rtsgt's modules (and packages) the help must not import: the numeric core, the pipeline,
#: the run directory's reader and writer, the reports.
HEAVY_RTSGT = ("rtsgt.pipeline", "rtsgt.report", "rtsgt.io.run_dir", "rtsgt.calibration",
               "rtsgt.checks", "rtsgt.evaluation", "rtsgt.simulation", "rtsgt.planning",
               "rtsgt.interpolation", "rtsgt.pose", "rtsgt.filtering", "rtsgt.noise",
               "rtsgt.options", "rtsgt.record", "rtsgt.stats", "rtsgt.batch", "rtsgt.types",
               "rtsgt.app")

#: Renders the help of the application and of each command, then prints the modules loaded.
HELP_SCRIPT = """
import json, sys
import typer
from typer.testing import CliRunner
from rtsgt.cli.main import app
runner = CliRunner()
names = sorted(typer.main.get_command(app).commands)
for args in [["--help"], *([name, "--help"] for name in names)]:
    result = runner.invoke(app, args)
    assert result.exit_code == 0 and "Usage: " in result.output, (args, result.output)
print(json.dumps({"commands": names, "modules": sorted(sys.modules)}))
"""

#: Runs ``rtsgt run`` with the arguments of argv, then prints the modules loaded.
RUN_SCRIPT = """
import json, sys
from typer.testing import CliRunner
from rtsgt.cli.main import app
result = CliRunner().invoke(app, ["run", *sys.argv[1:]])
assert result.exit_code == 0, result.output
print(json.dumps(sorted(sys.modules)))
"""


def _modules_of(script: str, *args: str) -> object:
    p = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    return json.loads(p.stdout.strip().splitlines()[-1])


def _heavy(modules: list[str]) -> list[str]:
    return [m for m in modules
            if m.split(".")[0] in HEAVY_PACKAGES
            or any(m == h or m.startswith(h + ".") for h in HEAVY_RTSGT)]


def test_help_of_every_command_imports_nothing_heavy():
    out = _modules_of(HELP_SCRIPT)
    assert {"run", "evaluate", "batch", "calibrate", "analyze"} <= set(out["commands"])
    assert "rtsgt.cli.batch" in out["modules"]  # the modules were imported, lightly
    assert _heavy(out["modules"]) == []


def test_run_without_report_never_imports_matplotlib(tmp_path):
    sim = simulate_deployment(SimulationConfig(duration_s=30.0), np.random.default_rng(5))
    toml = write_deployment(sim, tmp_path / "deployment")
    out = tmp_path / "run"
    modules = _modules_of(RUN_SCRIPT, str(toml), "-o", str(out), "--engine", "linear", "-q")
    assert "rtsgt.pipeline" in modules and (out / "summary.json").is_file()  # it ran
    assert not (out / "report.html").exists()
    assert [m for m in modules if m.split(".")[0] == "matplotlib"] == []


BLAS_SCRIPT = """
import json, os, sys
sys.argv = ["rtsgt", "--version"]
from rtsgt.cli import entry
try:
    entry.main()
except SystemExit:
    pass
print(json.dumps({k: os.environ.get(k) for k in entry.BLAS_THREADS}))
"""


def test_the_command_line_runs_blas_on_one_thread_unless_told_otherwise():
    """The console script sets one BLAS thread before numpy loads (docs/benchmarks.md#speed);
    a user's own setting wins."""
    import os

    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    for given, expected in ((None, "1"), ("2", "2")):
        e = dict(env) if given is None else {**env, "OPENBLAS_NUM_THREADS": given}
        p = subprocess.run([sys.executable, "-c", BLAS_SCRIPT], capture_output=True,
                           text=True, timeout=120, env=e)
        assert p.returncode == 0, p.stderr
        got = json.loads(p.stdout.strip().splitlines()[-1])
        assert got["OPENBLAS_NUM_THREADS"] == expected and got["OMP_NUM_THREADS"] == "1"
