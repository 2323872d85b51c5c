"""``rtsgt interpolate``: GP interpolation of one prism track at query times, with
covariance, Qc chosen as ``rtsgt run`` chooses it (:func:`rtsgt.interpolation.prisms.fit_prism_gp`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.choices import DEFAULT_MAX_GAP_S, DEFAULT_PRIOR, DEFAULT_QC
from rtsgt.cli.common import checked_options, usage_error
from rtsgt.errors import InputError
from rtsgt.io.output_dir import check_output_file

if TYPE_CHECKING:
    import numpy as np

    from rtsgt.interpolation import GPTrack


def rate_times(gp: GPTrack, rate_hz: float) -> tuple[np.ndarray, int]:
    """Times ``t_0 + k / rate`` inside the track, shape (Q,), and how many grid times fell
    in gaps longer than ``max_gap_s`` (dropped)."""
    import numpy as np

    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"Expected --rate > 0 Hz, got {rate_hz!r}")
    span = gp.t[-1] - gp.t[0]
    n = int(math.floor(span * rate_hz * (1 + 1e-12))) + 1
    if n > 50_000_000:
        raise InputError(f"--rate {rate_hz} Hz over {span:.1f} s gives {n} times; too many")
    times = gp.t[0] + np.arange(n) / rate_hz
    times = times[times <= gp.t[-1]]
    ok = gp.supported(times)
    return times[ok], int(np.sum(~ok))


def parse_qc(text: str | None) -> float | str:
    """``--qc``: ``loo``, ``likelihood`` or a number (m^2/s^3), by the configuration's rule."""
    from rtsgt.options import QC_METHODS, InterpolationOptions

    text = DEFAULT_QC if text is None else str(text).strip()
    try:
        value = text if text in QC_METHODS else float(text)
    except ValueError:
        raise usage_error(f"expected {', '.join(QC_METHODS)} or a number (m^2/s^3), got "
                          f"{text!r}", "--qc") from None
    try:
        InterpolationOptions(qc=value)
    except InputError as exc:
        raise usage_error(exc.bare_message, "--qc") from None
    return value


def interpolate_file(
    track_path: Path,
    *,
    at: Path | None = None,
    rate: float | None = None,
    qc: float | str = DEFAULT_QC,
    max_gap: float = DEFAULT_MAX_GAP_S,
    prior: str = DEFAULT_PRIOR,
) -> tuple[str, GPTrack, dict, int]:
    """Fit the track of ``track_path`` (``qc``, ``prior`` as ``rtsgt run``) and answer the
    queries; returns the posterior as track CSV text, the GP, how Qc was chosen and the
    number of rate-grid times dropped in long gaps (0 with ``at``)."""
    import numpy as np

    from rtsgt.interpolation.prisms import fit_prism_gp
    from rtsgt.io.track_csv import read_query_times, read_track_csv, track_csv_text
    from rtsgt.options import InterpolationOptions

    if (at is None) == (rate is None):
        raise usage_error("give exactly one of --at TIMES.txt and --rate HZ", "--at / --rate")
    # the rule [interpolation] meets (inf: no gap limit)
    checked_options(InterpolationOptions, {"rate_hz": "--rate", "max_gap_s": "--max-gap",
                    "prior": "--prior"}, rate_hz=rate, max_gap_s=max_gap, prior=prior)
    track = read_track_csv(track_path)
    try:
        gp, info = fit_prism_gp(track, qc, max_gap, str(track_path), prior)
    except InputError as exc:  # e.g. a single measurement: say which file
        if exc.path is None:
            raise InputError(exc.bare_message, track_path) from None
        raise
    if at is not None:
        times, lines = read_query_times(at, with_lines=True)
        _check_query_times(gp, times, lines, at)
        n_skipped = 0
    else:
        times, n_skipped = rate_times(gp, rate)
        if times.size == 0:
            raise InputError(f"No --rate {rate} Hz grid time inside the track", track_path)
    res = gp.query(np.sort(times))
    return track_csv_text((res.t, res.position, res.position_cov)), gp, info, n_skipped


def _check_query_times(gp: GPTrack, times: np.ndarray, lines: np.ndarray, path: Path) -> None:
    """Query times must be distinct and supported: name the line of the first that is not."""
    import numpy as np

    order = np.argsort(times, kind="stable")
    dup = np.flatnonzero(np.diff(times[order]) == 0)
    if dup.size:
        i, j = sorted((order[dup[0]], order[dup[0] + 1]))
        raise InputError(f"duplicated query time {float(times[j])!r} s (same as line {lines[i]}): "
                         "the output is a track, its times must be distinct", path, int(lines[j]))
    ok = gp.supported(times)
    if ok.all():
        return
    i = int(np.flatnonzero(~ok)[0])
    tau, t = float(times[i]), gp.t
    if tau < t[0] or tau > t[-1]:
        why = f"outside the track ({float(t[0])!r} s to {float(t[-1])!r} s)"
    else:
        k = int(np.searchsorted(t, tau, side="right")) - 1
        why = (
            f"inside a gap of {t[k + 1] - t[k]:.3f} s between measurements at "
            f"{float(t[k])!r} s and {float(t[k + 1])!r} s, longer than --max-gap "
            f"{gp.max_gap_s!r} s"
        )
    raise InputError(
        f"query time {tau!r} s is {why}; {int((~ok).sum())} of {times.size} query times "
        "are not supported by the track (no extrapolation)", path, int(lines[i]))


def _describe_qc(gp: GPTrack, info: dict) -> str:
    import numpy as np

    diag = np.diag(gp.qc)
    unit = "m^2/s^5" if gp.prior == "wnoj" else "m^2/s^3"
    if np.allclose(gp.qc, diag[0] * np.eye(3), rtol=0, atol=0):
        value = f"{diag[0]:.6g} {unit} (isotropic)"
    else:
        value = "diag(" + ", ".join(f"{v:.6g}" for v in diag) + f") {unit}"
    # the prior, and with --prior select the windows' scores that chose it
    prior = f"; {gp.prior.upper()} prior"
    if "prior_choice" in info:
        pc = info["prior_choice"]
        prior += " (log predictive density of the held-out windows: " + ", ".join(
            f"{p.upper()} {pc[p]['log_density']:.1f}" for p in ("wnoa", "wnoj")
            if pc[p]["log_density"] is not None) + ")"
    if info["method"] == "loo":
        return (f"qc = {value}, fitted by leave-one-out cross-validation; log-likelihood "
                f"{gp.log_likelihood:.3f}{prior}")
    if gp.qc_fit is None:
        return f"qc = {value}, given; log-likelihood {gp.log_likelihood:.3f}{prior}"
    fit = gp.qc_fit
    state = "converged" if fit.converged else f"NOT converged: {fit.message}"
    return (
        f"qc = {value}, fitted by maximum marginal likelihood ({fit.mode}, {state}, "
        f"{fit.n_evaluations} evaluations); log-likelihood {gp.log_likelihood:.3f}{prior}"
    )


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("interpolate")
    def interpolate(
        track: Path = typer.Argument(
            ..., help="Prism track CSV: t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz."),
        at: Path | None = typer.Option(None, "--at", help="File of query times, one per line (s)."),
        rate: float | None = typer.Option(
            None, "--rate", help="Query on a regular grid at this rate (Hz), skipping long gaps."),
        qc: str = typer.Option(
            DEFAULT_QC, "--qc",
            help="Qc, as rtsgt run chooses it: 'loo' (leave-one-out per axis, calibrated for "
            "interpolation), 'likelihood' (maximum marginal likelihood, isotropic) or a "
            "number, the isotropic power spectral density in m^2/s^3."),
        max_gap: float = typer.Option(DEFAULT_MAX_GAP_S, "--max-gap",
                                      help="Refuse queries across longer gaps (s)."),
        prior: str = typer.Option(
            DEFAULT_PRIOR, "--prior",
            help="GP motion prior: wnoa (white noise on acceleration, the paper's), wnoj (on "
            "jerk) or select (the one whose held-out windows of 1-2 s are predicted " "better)."),
        out: Path | None = typer.Option(None, "--out", "-o",
                                        help="Output CSV (default: standard output)."),
    ) -> None:
        """Interpolate a prism track (exact GP, WNOA or WNOJ prior) at query times, with
        covariance."""
        from rtsgt.io._parse import atomic_write_text

        qc_value = parse_qc(qc)
        if out is not None:
            check_output_file(out, option="--out", inputs=[p for p in (track, at) if p],
                              written_by_rtsgt=_is_track_csv)
        text, gp, info, n_skipped = interpolate_file(track, at=at, rate=rate, qc=qc_value,
                                                     max_gap=max_gap, prior=prior)
        typer.echo(_describe_qc(gp, info), err=True)
        if n_skipped:
            typer.echo(f"skipped {n_skipped} grid times inside gaps longer than {max_gap} s",
                       err=True)
        if out is None:
            typer.echo(text, nl=False)
        else:
            atomic_write_text(out, text)


def _is_track_csv(head: str) -> bool:
    """Whether a file's first line is the header of a track CSV (what --out writes)."""
    from rtsgt.io.track_csv import TRACK_COLUMNS

    first = head.split("\n", 1)[0].strip().lower()
    return first.split(",")[: len(TRACK_COLUMNS)] == list(TRACK_COLUMNS)


__all__ = ["interpolate_file", "rate_times", "register"]
