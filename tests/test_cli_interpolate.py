"""`rtsgt interpolate TRACK.csv (--at TIMES.txt | --rate HZ) [--qc loo|likelihood|Q] [--out OUT.csv]`."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.cli import main as cli_main
from rtsgt.cli.interpolate import rate_times
from rtsgt.cli.main import app
from rtsgt.interpolation import fit_track
from rtsgt.interpolation.loo import fit_qc_loo
from rtsgt.io.track_csv import TRACK_COLUMNS, read_track_csv, write_track_csv

HEADER = "t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz"
runner = CliRunner()


@pytest.fixture()
def track_file(tmp_path) -> Path:
    """A simulated prism track (~0.4 s, mm covariances, one 6 s gap) in the CSV layout."""
    rng = np.random.default_rng(42)
    n = 60
    t = 1.668e9 + np.cumsum(rng.uniform(0.35, 0.45, n))
    t[35:] += 6.0
    xyz = np.array([100.0, -50.0, 3.0]) + np.cumsum(rng.normal(size=(n, 3)) * 0.05, axis=0)
    a = rng.normal(size=(n, 3, 3)) * 1.5e-3
    cov = a @ np.swapaxes(a, 1, 2) + 1e-6 * np.eye(3)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    path = tmp_path / "prism1.csv"
    write_track_csv(path, (t, xyz, cov))
    return path


def read_output(text: str) -> np.ndarray:
    lines = text.splitlines()
    assert lines[0] == HEADER
    return np.array([[float(v) for v in line.split(",")] for line in lines[1:]])


def library(track_file, times, **kw):
    gp = fit_track(read_track_csv(track_file), **kw)
    res = gp.query(np.sort(times))
    flat = res.position_cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    return gp, np.column_stack([res.t, res.position, flat])


def invoke(*args):
    return runner.invoke(app, ["interpolate", *map(str, args)])


def loo_qc(track_file):
    """The Qc rtsgt run would choose for this track: leave-one-out, per axis."""
    tr = read_track_csv(track_file)
    return fit_qc_loo((tr.t, tr.xyz, tr.cov), mode="per-axis", max_gap_s=3.0).qc


def test_rate_with_the_runs_qc_policy_equals_the_library(track_file):
    """By default Qc is chosen as rtsgt run chooses it: leave-one-out, per axis."""
    result = invoke(track_file, "--rate", 5)
    assert result.exit_code == 0, result.output
    out = read_output(result.stdout)
    qc = loo_qc(track_file)
    gp, _ = library(track_file, [], qc=qc)
    times, skipped = rate_times(gp, 5.0)
    _, expected = library(track_file, times, qc=qc)
    np.testing.assert_array_equal(out, expected)  # shortest round-trip decimals: exact
    assert skipped > 0 and np.all(gp.supported(out[:, 0]))
    np.testing.assert_allclose(np.diff(out[:, 0])[:20], 0.2, atol=1e-6)
    assert "fitted by leave-one-out cross-validation" in result.stderr
    assert "diag(" + ", ".join(f"{v:.6g}" for v in np.diag(qc)) in result.stderr
    assert f"skipped {skipped} grid times" in result.stderr
    assert HEADER not in result.stderr
    assert invoke(track_file, "--rate", 5, "--qc", "loo").stdout == result.stdout


def test_at_times_with_given_qc_and_out_file(track_file, tmp_path):
    t = read_track_csv(track_file).t
    times = np.array([t[10] + 0.1, t[0], t[3] + 0.05, t[-1], t[20]])  # unsorted, knots, ends
    tf = tmp_path / "times.txt"
    tf.write_text("# query times\n" + "\n".join(repr(float(x)) for x in times) + "\n\n")
    out = tmp_path / "out.csv"
    result = invoke(track_file, "--at", tf, "--qc", 0.02, "--out", out)
    assert result.exit_code == 0, result.output
    assert result.stdout == ""
    assert "qc = 0.02 m^2/s^3 (isotropic), given" in result.stderr
    got = read_output(out.read_text())
    _, expected = library(track_file, times, qc=0.02)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got[:, 0], np.sort(times))
    # the output reads back as a prism track
    assert len(read_track_csv(out)) == times.size
    # the same on stdout
    again = invoke(track_file, "--at", tf, "--qc", 0.02)
    assert again.stdout == out.read_text()


def test_likelihood_qc_equals_the_library(track_file):
    a = invoke(track_file, "--rate", 2, "--qc", "likelihood")
    assert a.exit_code == 0, a.output
    assert "fitted by maximum marginal likelihood (isotropic" in a.stderr
    gp, _ = library(track_file, [], fit_qc=True)
    times, _ = rate_times(gp, 2.0)
    _, expected = library(track_file, times, fit_qc=True)
    np.testing.assert_array_equal(read_output(a.stdout), expected)
    bad = invoke(track_file, "--rate", 2, "--qc", "cv")
    assert bad.exit_code == 2 and "--qc" in bad.stderr


def test_the_same_qc_as_rtsgt_run_on_the_same_track(track_file):
    """One Qc policy: rtsgt interpolate and the pipeline's fit_gps choose the same Qc."""
    from rtsgt.interpolation.prisms import fit_gps
    from rtsgt.options import InterpolationOptions

    tr = read_track_csv(track_file)
    gps = fit_gps({"1": tr}, InterpolationOptions(gp_noise="all"))
    r = invoke(track_file, "--rate", 2)
    assert "diag(" + ", ".join(f"{v:.6g}" for v in np.diag(gps["1"].qc)) in r.stderr


def test_max_gap_option(track_file):
    wide = invoke(track_file, "--rate", 5, "--qc", 0.05, "--max-gap", 10)
    narrow = invoke(track_file, "--rate", 5, "--qc", 0.05)
    assert len(read_output(wide.stdout)) > len(read_output(narrow.stdout)) + 25
    assert "skipped" not in wide.stderr


# --------------------------------------------------------------------------------------------
# Bad input: one line `error: FILE:LINE: ...`, exit code 1, no output file
# --------------------------------------------------------------------------------------------


def run_main(monkeypatch, capsys, *args):
    """The application the console script runs, in-process: exit code, stdout, stderr."""
    monkeypatch.setattr(sys, "argv", ["rtsgt", "interpolate", *map(str, args)])
    with pytest.raises(SystemExit) as exc:
        cli_main.app()
    cap = capsys.readouterr()
    return exc.value.code, cap.out, cap.err


def corrupt(track_file, tmp_path, line_no, edit):
    """A copy of the track with line ``line_no`` (1-based) replaced by ``edit(fields)``."""
    lines = track_file.read_text().splitlines()
    lines[line_no - 1] = ",".join(edit(lines[line_no - 1].split(",")))
    p = tmp_path / "bad.csv"
    p.write_text("\n".join(lines) + "\n")
    return p


def make_bad(case, track_file, tmp_path):
    lines = track_file.read_text().splitlines()
    if case == "missing":
        return tmp_path / "nope.csv"
    if case == "header":
        return corrupt(track_file, tmp_path, 1, lambda f: [c.replace("cov_xy", "cov_yx") for c in f])
    if case == "nan":
        return corrupt(track_file, tmp_path, 5, lambda f: f[:2] + ["nan"] + f[3:])
    if case == "columns":
        return corrupt(track_file, tmp_path, 7, lambda f: f[:-1])
    if case == "duplicate":
        t_prev = lines[2].split(",")[0]
        return corrupt(track_file, tmp_path, 4, lambda f: [t_prev] + f[1:])
    if case == "not_spd":
        return corrupt(track_file, tmp_path, 9,
                       lambda f: f[:4] + ["1e-6", "0", "0", "-1e-6", "0", "1e-6"])
    if case == "one_line":
        p = tmp_path / "bad.csv"
        p.write_text("\n".join(lines[:2]) + "\n")
        return p
    raise AssertionError(case)


BAD_TRACKS = {
    "missing": r"nope.csv: file not found$",
    "header": r"bad.csv:1: expected the header to start with",
    "nan": r"bad.csv:5: expected a finite number in column 'y', got 'nan'$",
    "columns": r"bad.csv:7: expected .*columns",
    "duplicate": r"bad.csv:4: duplicated timestamp",
    "not_spd": r"bad.csv:9: expected a symmetric positive definite covariance",
    "one_line": r"bad.csv: Expected at least 2 measurements to fit a track, got 1$",
}


@pytest.mark.parametrize("case", sorted(BAD_TRACKS))
def test_bad_track_gives_one_error_line_and_no_output(case, track_file, tmp_path,
                                                       monkeypatch, capsys):
    pattern = BAD_TRACKS[case]
    bad = make_bad(case, track_file, tmp_path)
    out = tmp_path / "out.csv"
    code, stdout, stderr = run_main(monkeypatch, capsys, bad, "--rate", 5, "--out", out)
    assert code == 1
    assert stdout == ""
    assert stderr.startswith("error: ") and stderr.count("\n") == 1, stderr
    assert re.search(pattern, stderr.rstrip("\n")), stderr
    assert not out.exists()
    assert not list(tmp_path.glob(".out.csv.*"))  # no temporary file left behind
    # CliRunner: the same InputError, exit code 1
    result = invoke(bad, "--rate", 5, "--out", out)
    assert result.exit_code == 1 and result.stderr.startswith("error: ")
    assert not out.exists()


def test_existing_out_file_is_left_untouched_on_error(track_file, tmp_path, monkeypatch,
                                                      capsys):
    out = tmp_path / "out.csv"
    previous = ",".join(TRACK_COLUMNS) + "\n1,0,0,0,1,0,0,1,0,1\n"  # an earlier output
    out.write_text(previous)
    tf = tmp_path / "times.txt"
    t = read_track_csv(track_file).t
    tf.write_text(f"{float(t[1])!r}\n{float(t[2])!r}\n{float(t[-1]) + 100.0!r}\n")
    code, _, stderr = run_main(monkeypatch, capsys, track_file, "--at", tf, "--out", out)
    assert code == 1
    assert stderr.startswith(f"error: {tf}:3: query time ") and "outside the track" in stderr
    assert out.read_text() == previous


@pytest.mark.parametrize(
    ("times_text", "pattern"),
    [
        ("{a}\n{gap}\n", r"times.txt:2: query time .* inside a gap of 6\.\d+ s .*--max-gap 3.0 s"),
        ("{a}\n# comment\n{a}\n", r"times.txt:3: duplicated query time .*same as line 1"),
        ("{a}\nabc\n", r"times.txt:2: expected a number in column 't', got 'abc'"),
        ("{a}\nnan\n", r"times.txt:2: expected a finite number"),
        ("{a} {a}\n", r"times.txt:1: expected 1 whitespace-separated columns"),
        ("\n# nothing\n", r"times.txt: empty file"),
    ],
)
def test_bad_query_times(times_text, pattern, track_file, tmp_path, monkeypatch, capsys):
    t = read_track_csv(track_file).t
    tf = tmp_path / "times.txt"
    tf.write_text(times_text.format(a=repr(float(t[1])), gap=repr(float(t[34] + 3.0))))
    code, stdout, stderr = run_main(monkeypatch, capsys, track_file, "--at", tf, "--qc", 0.1)
    assert code == 1 and stdout == ""
    assert stderr.startswith("error: ") and stderr.count("\n") == 1
    assert re.search(pattern, stderr), stderr


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        ((), "exactly one of --at TIMES.txt and --rate HZ"),
        (("--rate", 5, "--at", "x.txt"), "exactly one of --at"),
        (("--rate", 5, "--qc", "cv"), "expected loo, likelihood or a number"),
        (("--rate", 0), r"--rate: expected a finite rate_hz > 0 Hz"),
        (("--rate", 5, "--qc", -1), r"expected qc > 0"),
        (("--rate", 5, "--max-gap", 0), r"--max-gap: expected max_gap_s > 0"),
    ],
)
def test_bad_options(args, pattern, track_file, monkeypatch, capsys):
    """Bad option values are usage errors: exit status 2, one line."""
    code, _, stderr = run_main(monkeypatch, capsys, track_file, *args)
    assert code == 2 and stderr.startswith("error: ") and stderr.count("\n") == 1
    assert pattern in stderr.replace("\\", ""), stderr


# --------------------------------------------------------------------------------------------
# The installed console script
# --------------------------------------------------------------------------------------------


def _rtsgt_executable() -> str:
    exe = Path(sys.executable).with_name("rtsgt")
    found = str(exe) if exe.exists() else shutil.which("rtsgt")
    if found is None:
        pytest.skip("the rtsgt console script is not installed")
    return found


def test_console_script(track_file, tmp_path):
    exe = _rtsgt_executable()
    out = tmp_path / "out.csv"
    proc = subprocess.run([exe, "interpolate", str(track_file), "--rate", "5", "--qc", "0.05",
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    gp = fit_track(read_track_csv(track_file), qc=0.05)
    times, _ = rate_times(gp, 5.0)
    _, expected = library(track_file, times, qc=0.05)
    np.testing.assert_array_equal(read_output(out.read_text()), expected)
    bad = corrupt(track_file, tmp_path, 5, lambda f: f[:1] + ["nan"] + f[2:])
    out2 = tmp_path / "out2.csv"
    proc = subprocess.run([exe, "interpolate", str(bad), "--rate", "5", "--out", str(out2)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stdout == ""
    assert proc.stderr == (f"error: {bad}:5: expected a finite number in column 'x', "
                           "got 'nan'\n")
    assert not out2.exists()


def test_prior_option(track_file):
    """--prior: the WNOJ prior's Qc is in m^2/s^5; "select" fits both and says their window
    scores; the output is the library's fit with the prior chosen."""
    from rtsgt.interpolation.prisms import fit_prism_gp

    j = invoke(track_file, "--rate", 2, "--prior", "wnoj")
    assert j.exit_code == 0, j.output
    assert "m^2/s^5" in j.stderr and "WNOJ prior" in j.stderr
    s = invoke(track_file, "--rate", 2, "--prior", "select")
    assert s.exit_code == 0, s.output
    assert "log predictive density of the held-out windows: WNOA" in s.stderr
    tr = read_track_csv(track_file)
    gp, info = fit_prism_gp(tr, "loo", 3.0, "t", "select")
    assert info["prior_choice"]["chosen"] == gp.prior
    times, _ = rate_times(gp, 2.0)
    res = gp.query(np.sort(times))
    np.testing.assert_array_equal(read_output(s.stdout)[:, 1:4], res.position)
    bad = invoke(track_file, "--rate", 2, "--prior", "singer")
    assert bad.exit_code == 2 and "--prior" in bad.stderr
