"""Helpers shared by the commands: progress display and run summaries (CLI edge only)."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from rtsgt.calibration.gcp import (
    CALIBRATION_METHOD_NAMES,
    CALIBRATION_MODEL_NAMES,
    CALIBRATION_WEIGHTING_NAMES,
)
from rtsgt.errors import InputError
from rtsgt.record import MIN_POSE_PRISMS, PositionRunRecord, RunRecord


def tau_text(correlation: dict) -> str:
    """A static-noise correlation time with its 95 % interval (:mod:`rtsgt.checks.static`),
    e.g. ``"2.5 s (1.1-6.0 s)"`` or ``"5.0 s (at least 2.1 s)"``."""
    tau, iv = correlation["correlation_time_s"], correlation.get("correlation_time_95_s")
    if not iv:
        return f"{tau:.1f} s"
    return f"{tau:.1f} s (" + (f"{iv[0]:.1f}-{iv[1]:.1f} s)" if iv[1] is not None
                               else f"at least {iv[0]:.1f} s)")


def usage_error(message: str, option: str) -> typer.BadParameter:
    """A bad value of a command-line option, for ``raise`` (exit status 2, see
    :mod:`rtsgt.cli.main`)."""
    if message[:1].isupper() and message[1:2].islower():  # "Expected ..." -> "expected ..."
        message = message[0].lower() + message[1:]
    return typer.BadParameter(message, param_hint=option)


def checked_options(build: Callable[..., object], names: dict[str, str], **values) -> dict:
    """The given (not None) command-line values, each checked by the rule of the options
    ``build`` makes (a record whose ``__post_init__`` raises :class:`~rtsgt.errors.InputError`:
    the rule the configuration file's values meet too); a bad one is a usage error naming
    its option (``names``: field -> option)."""
    changes = {k: v for k, v in values.items() if v is not None}
    for key, value in changes.items():
        try:
            build(**{key: value})
        except InputError as exc:
            raise usage_error(exc.bare_message, names[key]) from None
    return changes


def echo_err(msg: str) -> None:
    """A line on stderr."""
    typer.echo(msg, err=True)


class Stages:
    """A progress display of pipeline stages on stderr (a spinner and the elapsed time).

    Call the object with a stage name when the stage starts; nothing is shown with ``quiet``.
    """

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.console = Console(stderr=True)
        self._status = None
        self._name = None
        self._t0 = 0.0

    def __enter__(self) -> Stages:
        if not self.quiet:
            self._status = self.console.status("starting")
            self._status.__enter__()
        return self

    def __call__(self, stage: str) -> None:
        self._finish()
        self._name, self._t0 = stage, time.perf_counter()
        if self._status is not None:
            self._status.update(f"{stage} ...")

    def _finish(self) -> None:
        if self._name is not None and not self.quiet:
            elapsed = time.perf_counter() - self._t0
            self.console.print(f"  {self._name}: {elapsed:.2f} s", highlight=False)
        self._name = None

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self._finish()
        if self._status is not None:
            self._status.__exit__(*exc)


def print_run_summary(record: RunRecord | PositionRunRecord, out) -> None:
    """A short table of what a run produced (a position-only run: its prisms' positions)."""
    console = Console()
    table = Table(title=f"rtsgt run: {record.name}", show_header=False)
    positions = isinstance(record, PositionRunRecord)
    gt = None if positions else record.groundtruth
    if positions:
        t = record.prisms_t
        n = len(record.prism_ids)
        table.add_row("ground truth", f"positions of prism{'s' if n > 1 else ''} "
                      f"{', '.join(record.prism_ids)} (a pose needs {MIN_POSE_PRISMS} tracked "
                      "prisms): prisms/prism<i>.csv")
        table.add_row("positions", str(t.size))
        for i, pid in enumerate(record.prism_ids):
            sig = np.sqrt(np.trace(record.prisms_cov[:, i], axis1=1, axis2=2)) * 1e3
            table.add_row(f"median sigma prism {pid} (sqrt trace)", f"{np.median(sig):.2f} mm")
        if t.size:
            table.add_row("time span", f"{t[-1] - t[0]:.1f} s")
    else:
        table.add_row("poses kept / queried", f"{len(gt)} / {record.prisms_t.shape[0]}")
    if gt is not None and len(gt):
        sig_t = np.sqrt(np.trace(gt.cov[:, :3, :3], axis1=1, axis2=2)) * 1e3
        sig_r = np.sqrt(np.trace(gt.cov[:, 3:, 3:], axis1=1, axis2=2)) * 1e3
        table.add_row("median sigma translation (sqrt trace)", f"{np.median(sig_t):.2f} mm")
        table.add_row("median sigma rotation (sqrt trace)", f"{np.median(sig_r):.3f} mrad")
        table.add_row("time span", f"{gt.t[-1] - gt.t[0]:.1f} s")
    for pid, qc in record.qc.items():
        # the prior of each prism's GP: white noise on the acceleration (Qc in m^2/s^3) or on
        # the jerk (m^2/s^5)
        prior = record.prior.get(pid, "wnoa")
        unit = "m^2/s^5" if prior == "wnoj" else "m^2/s^3"
        table.add_row(f"Qc prism {pid} (x, y, z), GP prior",
                      ", ".join(f"{q:.2e}" for q in np.diag(qc)) + f" {unit}, {prior.upper()}")
    if not positions:
        reasons, counts = np.unique(record.rejected_reason, return_counts=True)
        for reason, count in zip(reasons, counts, strict=True):
            table.add_row(f"rejected: {reason}", str(int(count)))
    read = None if record.computation is None else record.computation.filter_reports.get("input")
    if read is not None:  # the messages of a bag the reader removed, by status
        gone = ", ".join(f"{k} {v}" for k, v in read.removed.items() if v)
        table.add_row("bag messages valid / read", f"{read.n_kept} / {read.n_in}"
                      + (f" (removed: {gone})" if gone else ""))
    n_left = int(np.sum(record.removed.stage == "module4"))
    if n_left:
        table.add_row("measurements left out of the GPs (distance windows)", str(n_left))
    # the self-checks (rtsgt.checks): the GCP fit's variance factor per station, the
    # inter-prism distances' mean z^2 and the block cross-validation's NEES / dof, each with
    # its 95 % interval, and the noise on the static stretches per prism and component
    # (Bonferroni intervals)
    gcp = record.self_checks.get("gcp_fit", {})
    if gcp.get("model"):
        table.add_row("calibration model", CALIBRATION_MODEL_NAMES[gcp["model"]]
                      + (f"; {CALIBRATION_WEIGHTING_NAMES[gcp['weighting']]}"
                         if gcp.get("weighting") else ""))
    table.add_row("calibration method",
                  CALIBRATION_METHOD_NAMES[record.options.calibration.method])
    dyn = record.self_checks.get("dynamic_calibration")
    if dyn:
        lo, hi = dyn["interval_95"]
        table.add_row(f"self-check {dyn['method']} calibration ({dyn['samples']} samples)",
                      f"{dyn['variance_factor']:.2f}, 95 % [{lo:.2f}, {hi:.2f}]: "
                      f"{dyn['verdict']}")
        for s, v in dyn["clock_offset_ms"].items():
            table.add_row(f"clock offset, station {s}",
                          f"{v:+.2f} ± {dyn['clock_sigma_ms'][s]:.2f} ms")
        for s, v in dyn.get("gcp_agreement", {}).items():
            table.add_row(f"dynamic against GCP calibration, station {s}",
                          f"chi2 {v['chi2']:.1f} ({v['dof']} dof), p = {v['p_value']:.2g}: "
                          f"{v['verdict']}")
    for s, v in gcp.get("stations", {}).items():
        if v.get("dof"):
            lo, hi = v["interval_95"]
            table.add_row(f"self-check GCP fit, station {s}",
                          f"{v['variance_factor']:.2f}, 95 % [{lo:.2f}, {hi:.2f}]: {v['verdict']}")
    added = gcp.get("added_shot_sigma_mm", {})
    if any(added.values()):
        table.add_row("calibration: added per shot", f"{added['horizontal']:.2f} mm horizontal, "
                      f"{added['vertical']:.2f} mm vertical")
    check = record.self_checks.get("inter_prism_distances", {})
    for name, v in [("whole run", check.get("overall")), *check.get("regimes", {}).items()]:
        if v and v.get("interval_95"):
            lo, hi = v["interval_95"]
            table.add_row(f"self-check z^2, {name} ({v['poses']} poses)",
                          f"{v['mean_z2']:.2f}, 95 % [{lo:.2f}, {hi:.2f}]: {v['verdict']}")
    # block cross-validation of the tracks (held-out windows), NEES / dof by regime
    cv = record.self_checks.get("block_cv", {})
    for name, v in [("whole run", cv.get("overall")), *cv.get("regimes", {}).items()]:
        if v and v.get("interval_95"):
            lo, hi = v["interval_95"]
            table.add_row(f"self-check block CV, {name} ({v['blocks']} windows)",
                          f"{v['nees_per_dof']:.2f}, 95 % [{lo:.2f}, {hi:.2f}]: {v['verdict']}")
    static = record.self_checks.get("static_noise", {})
    if static and not static.get("prisms"):
        table.add_row("self-check static", static.get("note", "no static stretch"))
    for pid, e in static.get("prisms", {}).items():
        for name in ("range", "horizontal", "vertical"):
            c = e[name]
            text = f"{c['observed_sigma_mm']:.2f} / {c['predicted_sigma_mm']:.2f} mm"
            lv, co = c["level"], c["correlation"]
            if lv.get("interval"):
                (lo, hi), (rlo, rhi) = lv["interval"], co["interval"]
                text += (f", ratio {lv['variance_ratio']:.2f} [{lo:.2f}, {hi:.2f}]: "
                         f"{lv['verdict']}; lag-1 {co['lag1']:.2f} [{rlo:.2f}, {rhi:.2f}]: "
                         f"{co['verdict']}")
                if co.get("correlation_time_s") is not None:
                    text += f", correlation time {tau_text(co)}"
            else:
                text += f": {lv['verdict']}"
            table.add_row(f"self-check static, prism {pid} {name}",
                          f"{e['samples']} samples, {text}")
    if static.get("confidence"):
        table.add_row("self-check static: intervals",
                      f"{100 * static['confidence']:.2f} % each ({static['tests']} tests, "
                      f"{100 * static['family_false_alarm']:.0f} % false alarms per run)")
    _correlated_rows(table, record.correlated_noise)
    _structure_rows(table, record.self_checks.get("inter_prism_structure", {}))
    table.add_row("output", str(out))
    console.print(table)


def _correlated_rows(table: Table, plan: dict) -> None:
    """The time-correlated noise the static-stretch check found, per prism, and whether the
    GPs carried it (:mod:`rtsgt.noise.correlated`): each component's variance factor with the
    correlated share and correlation time it comes from."""
    for pid, e in plan.get("prisms", {}).items():
        found = [(name, e[name]) for name in ("range", "horizontal", "vertical")
                 if e[name].get("rho") is not None]
        if not found:
            continue
        text = "; ".join(f"{name} x{c['factor']:.1f} (f {c['correlated_fraction']:.2f}, "
                         f"tau {c['correlation_time_s']:.1f} s)" for name, c in found)
        done = any(c["applied"] for _, c in found)
        table.add_row(f"correlated noise, prism {pid}",
                      f"white variance {'inflated' if done else 'not inflated (ignore)'}: "
                      f"{text}")


def _structure_rows(table: Table, check: dict) -> None:
    """The inter-prism residual structure check (:mod:`rtsgt.checks.structure`): each test's
    statistic against its critical value, and the clock offsets of the whole run."""
    ck, po = check.get("clock"), check.get("prism_orientation")
    if ck and ck.get("verdict"):
        table.add_row(f"self-check clock offsets ({ck.get('windows', 0)} windows)",
                      f"chi2/dof {ck['chi2_per_dof']:.2f}, critical {ck['critical']:.2f} "
                      f"({100 * ck['level']:.1f} %): {ck['verdict']}"
                      if ck.get("critical") else ck["verdict"])
    if po and po.get("verdict"):
        table.add_row("self-check prism orientation",
                      f"F {po['f']:.2f}, critical {po['critical']:.2f} "
                      f"({100 * po['level']:.1f} %): {po['verdict']}"
                      if po.get("f") is not None else po["verdict"])
    offsets = (ck or {}).get("offsets_ms", {})
    if offsets:
        table.add_row("clock offsets, whole run", ", ".join(
            f"{k}: {v['run']:+.2f} +- {v['sigma']:.2f} ms" for k, v in offsets.items()))
