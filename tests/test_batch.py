"""``rtsgt batch``: many deployments, serially or on Dask, resumable, one line per failure.

Four short simulated deployments with known, different truths (three deployment folders and
one TOML file beside its data folder) and one broken deployment (a TOML naming a file that is
not there) make a campaign folder. Then:

- ``--serial``, a local Dask cluster of two worker processes, and an existing cluster started
  as separate processes by the ``dask scheduler`` and ``dask worker`` programs give the same
  run directories byte for byte (``summary.json`` less its timings), whatever the scheduling
  and whichever other deployments are in the batch;
- the broken deployment is one ``failed:`` line and a row of the summary, the others complete,
  and the exit status is 1;
- a second call skips every complete deployment; a deleted run, a damaged one, an edited
  input or another base seed is run again;
- each deployment's seed comes from the base seed and its name by a stable hash;
- the summary table (CSV and HTML) holds what each run's ``summary.json`` says;
- without Dask, ``--serial`` works and the other modes say how to install it.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.batch import BatchTask, deployment_seed, find_deployments, is_complete, make_tasks
from rtsgt.cli.main import app
from rtsgt.errors import InputError
from rtsgt.io.batch_summary import BATCH_COLUMNS
from rtsgt.io.run_dir import read_summary
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

runner = CliRunner()
GOOD = ("d1", "d2", "d3", "d4")
#: The options every batch of these tests runs with (fast: the linear engine).
FAST = ("--engine", "linear", "-q")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """``d1/``, ``d2/``, ``d3/`` (deployment folders), ``d4.toml`` with its files in
    ``data4/``, ``broken.toml`` (its GCP file is missing), and ``notes/`` (no deployment)."""
    root = tmp_path_factory.mktemp("campaign")
    for k, name in enumerate(("d1", "d2", "d3", "data4"), start=1):
        sim = simulate_deployment(SimulationConfig(duration_s=30.0), np.random.default_rng(k))
        write_deployment(sim, root / name)
    toml = root / "data4" / "deployment.toml"
    (root / "d4.toml").write_text(re.sub(r'(?m)^file = "', 'file = "data4/', toml.read_text()))
    toml.unlink()
    (root / "broken.toml").write_text(
        (root / "d4.toml").read_text().replace("data4/GCP.txt", "data4/missing-GCP.txt"))
    (root / "notes").mkdir()
    (root / "notes" / "field-notes.txt").write_text("rain at 11:00\n")
    return root


def batch(*args) -> object:
    return runner.invoke(app, ["batch", *map(str, args)])


def run_files(run: Path) -> dict[str, bytes]:
    """Every file of a run directory, ``summary.json`` without its timings."""
    out = {}
    for p in sorted(run.rglob("*")):
        if p.is_file():
            data = p.read_bytes()
            if p.name == "summary.json":
                doc = json.loads(data)
                doc.pop("timings_s")
                data = json.dumps(doc, sort_keys=True).encode()
            out[p.relative_to(run).as_posix()] = data
    return out


def summary_rows(out: Path) -> dict[str, dict]:
    with open(out / "batch_summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(BATCH_COLUMNS)
    return {r["deployment"]: r for r in rows}


@pytest.fixture(scope="module")
def serial(campaign, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("serial") / "out"
    r = batch(campaign, "-o", out, "--serial", *FAST)
    assert r.exit_code == 1, r.output
    return out


def test_serial_batch_runs_the_good_deployments_and_reports_the_broken_one(serial, campaign):
    rows = summary_rows(serial)
    assert sorted(rows) == sorted((*GOOD, "broken"))
    for name in GOOD:
        assert rows[name]["status"] == "done" and rows[name]["error"] == ""
        assert int(rows[name]["seed"]) == deployment_seed(0, name)
        summary = read_summary(serial / name)
        assert summary.options.seed == deployment_seed(0, name)
        assert summary.options.pose.engine == "linear"
        doc = summary.document
        # the table is what summary.json says
        assert int(rows[name]["poses_kept"]) == doc["poses"]["kept"] > 50
        assert float(rows[name]["median_sigma_translation_mm"]) == (
            doc["median_uncertainty"]["translation_mm"])
        assert int(rows[name]["warnings"]) == len(doc["warnings"])
        clock = doc["self_checks"]["inter_prism_structure"]["clock"]["verdict"]
        assert rows[name]["check_clock"] == clock
    broken = rows["broken"]
    assert broken["status"] == "failed" and "missing-GCP.txt" in broken["error"]
    assert not (serial / "broken").exists()
    html = (serial / "batch_summary.html").read_text()
    for name in GOOD:
        assert f"<a href='{name}/summary.json'>{name}</a>" in html
    assert "missing-GCP.txt" in html and "<script" not in html
    # the four runs differ (different truths, different seeds)
    assert len({(serial / n / "groundtruth.tum").read_bytes() for n in GOOD}) == 4


def test_a_failure_is_one_line_and_the_exit_status_is_1(campaign, serial, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(serial, out)
    r = batch(campaign, "-o", out, "--serial", *FAST)
    assert r.exit_code == 1
    lines = r.output.strip().splitlines()
    failed = [s for s in lines if s.startswith("failed: ")]
    assert len(failed) == 1 and failed[0].startswith("failed: broken: ")
    assert "missing-GCP.txt" in failed[0] and "Traceback" not in r.output
    assert lines[-1] == (f"error: 1 of 5 deployments failed (the 'failed:' lines above); the "
                         f"others' runs and the summary are in {out}")
    assert any("skipped" in s and "notes" in s for s in lines if s.startswith("note: "))


@pytest.mark.slow
def test_a_local_dask_cluster_gives_the_serial_runs(campaign, serial, tmp_path):
    pytest.importorskip("dask.distributed")
    out = tmp_path / "dask"
    r = batch(campaign, "-o", out, "--workers", 2, *FAST)
    assert r.exit_code == 1, r.output
    assert [s for s in r.output.splitlines() if s.startswith("failed: ")] == [
        f"failed: broken: {summary_rows(serial)['broken']['error']}"]
    for name in GOOD:
        assert run_files(out / name) == run_files(serial / name), name
    a, b = summary_rows(out), summary_rows(serial)
    for name in (*GOOD, "broken"):
        for col in BATCH_COLUMNS:
            if col not in ("elapsed_s", "run_dir", "status"):
                assert a[name][col] == b[name][col], (name, col)


def _dask(*args: str, log: Path, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=subprocess.DEVNULL,
                            stderr=open(log, "w"), start_new_session=True,
                            env=None if env is None else {**os.environ, **env})


@pytest.mark.slow
def test_an_existing_dask_cluster_gives_the_serial_runs(campaign, serial, tmp_path):
    """A cluster started by the ``dask scheduler`` and ``dask worker`` programs, given by its
    address; two deployments only (their runs do not depend on the others)."""
    pytest.importorskip("dask.distributed")
    info = tmp_path / "scheduler.json"
    procs = [_dask("scheduler", "--scheduler-file", str(info), "--port", "0",
                   "--no-dashboard", log=tmp_path / "scheduler.log")]
    try:
        for _ in range(600):
            if info.is_file() and info.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(info.read_text())["address"]
        # the workers as docs/batch.md#dask says to start them
        config = tmp_path / "dask-config"
        config.mkdir()
        (config / "rtsgt.yaml").write_text("distributed:\n  nanny:\n    pre-spawn-environ:\n"
                                           "      MALLOC_TRIM_THRESHOLD_: null\n")
        procs.append(_dask("worker", "--scheduler-file", str(info), "--nworkers", "2",
                           "--nthreads", "1", "--no-dashboard", log=tmp_path / "worker.log",
                           env={"DASK_CONFIG": str(config)}))
        out = tmp_path / "cluster"
        r = batch(campaign / "d2", campaign / "d4.toml", "-o", out, "--scheduler", address,
                  *FAST)
        assert r.exit_code == 0, r.output
        assert sorted(summary_rows(out)) == ["d2", "d4"]
        for name in ("d2", "d4"):
            assert run_files(out / name) == run_files(serial / name), name
    finally:
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_resuming_skips_complete_runs_and_redoes_the_others(campaign, serial, tmp_path):
    out = tmp_path / "resume"
    shutil.copytree(serial, out)
    args = (campaign / "d1", campaign / "d2", campaign / "d3", "-o", out, "--serial", *FAST)
    before = {n: (out / n / "groundtruth.tum").stat().st_mtime_ns for n in ("d1", "d2", "d3")}
    r = batch(*args)
    assert r.exit_code == 0, r.output
    assert {n: r["status"] for n, r in summary_rows(out).items()} == dict.fromkeys(
        ("d1", "d2", "d3"), "skipped")
    assert before == {n: (out / n / "groundtruth.tum").stat().st_mtime_ns
                      for n in ("d1", "d2", "d3")}
    # a deleted run is run again, a damaged one (a file deleted) too: the same files
    shutil.rmtree(out / "d2")
    (out / "d3" / "reference.csv").unlink()
    r = batch(*args)
    assert r.exit_code == 0, r.output
    assert {n: r["status"] for n, r in summary_rows(out).items()} == {
        "d1": "skipped", "d2": "done", "d3": "done"}
    for name in ("d2", "d3"):
        assert run_files(out / name) == run_files(serial / name)
    # an input edited (a comment added to the GCP file) or another base seed: run again
    data = tmp_path / "d1"
    shutil.copytree(campaign / "d1", data)
    assert batch(data, "-o", tmp_path / "edit", "--serial", *FAST).exit_code == 0
    gcp = data / "GCP.txt"
    gcp.write_text(gcp.read_text() + "# checked on site\n")
    r = batch(data, "-o", tmp_path / "edit", "--serial", *FAST)
    assert summary_rows(tmp_path / "edit")["d1"]["status"] == "done"
    r = batch(data, "-o", tmp_path / "edit", "--serial", *FAST)
    assert summary_rows(tmp_path / "edit")["d1"]["status"] == "skipped"
    r = batch(data, "-o", tmp_path / "edit", "--serial", "--seed", 7, *FAST)
    assert r.exit_code == 0
    row = summary_rows(tmp_path / "edit")["d1"]
    assert row["status"] == "done" and int(row["seed"]) == deployment_seed(7, "d1")


def test_seeds_are_stable_and_differ_by_name_and_base_seed():
    # pinned: SHA-256 of "rtsgt-batch\0<base>\0<name>", first 8 bytes, top bit cleared
    assert deployment_seed(0, "d1") == 2091165119220954710
    assert deployment_seed(0, "20221110") == deployment_seed(0, "20221110")
    names = [f"deployment-{i}" for i in range(200)]
    seeds = {deployment_seed(0, n) for n in names}
    assert len(seeds) == 200 and all(0 <= s < 2**63 for s in seeds)
    assert deployment_seed(1, "d1") != deployment_seed(0, "d1")
    with pytest.raises(InputError):
        deployment_seed(-1, "d1")


def test_the_tasks_and_their_completeness(campaign, serial):
    deployments, notes = find_deployments([campaign], out=serial)
    assert [d.name for d in deployments] == ["broken", "d1", "d2", "d3", "d4"]
    # folders that are no deployment: said once each
    assert [n.split(":")[0] for n in notes] == [f"skipped {campaign / 'data4'}",
                                                 f"skipped {campaign / 'notes'}"]
    fast = {"engine": "linear"}
    tasks = {t.name: t for t in make_tasks(deployments, serial, options=fast)}
    assert all(isinstance(t, BatchTask) for t in tasks.values())
    assert is_complete(tasks["d1"]) and not is_complete(tasks["broken"])
    assert not is_complete(make_tasks(deployments[1:2], serial, base_seed=3, options=fast)[0])
    assert not is_complete(make_tasks(deployments[1:2], serial,
                                      options={"engine": "mc"})[0])


def test_bad_command_lines_and_outputs(campaign, tmp_path):
    r = batch(campaign, "-o", tmp_path / "x", "--serial", "--workers", 2)
    assert r.exit_code == 2 and "--serial" in r.output
    r = batch(campaign, "-o", tmp_path / "x", "--serial", "--engine", "fast")
    assert r.exit_code == 2 and "--engine" in r.output
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("mine\n")
    r = batch(campaign, "-o", mine, "--serial", *FAST)
    assert r.exit_code == 1 and "not an output of rtsgt batch" in r.output
    assert sorted(p.name for p in mine.iterdir()) == ["thesis.tex"]
    twice = tmp_path / "twice"
    twice.mkdir()
    shutil.copyfile(campaign / "d4.toml", twice / "d1.toml")
    r = batch(campaign / "d1", twice / "d1.toml", "-o", tmp_path / "y", "--serial", *FAST)
    assert r.exit_code == 1 and "2 deployments named 'd1'" in r.output


def test_without_dask_serial_works_and_the_rest_says_how_to_install_it(
        campaign, serial, tmp_path, monkeypatch):
    code = "import sys, rtsgt.cli.main, rtsgt.batch; print('dask' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.strip() == "False"
    monkeypatch.setitem(sys.modules, "dask", None)  # "import dask" now fails: not installed
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    out = tmp_path / "no-dask"
    r = batch(campaign / "d1", "-o", out, *FAST)
    assert r.exit_code == 1
    assert r.output.strip().splitlines()[-1].startswith("error: rtsgt batch runs the "
                                                        "deployments on Dask, which is not "
                                                        "installed: pip install 'rtsgt[batch]'")
    r = batch(campaign / "d1", "-o", out, "--serial", *FAST)
    assert r.exit_code == 0, r.output
    assert run_files(out / "d1") == run_files(serial / "d1")
