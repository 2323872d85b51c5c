"""Helpers of the commands: usage errors, warnings, progress display and run summaries
(light at import: what is heavy is imported by the helper that needs it)."""

from __future__ import annotations

import contextlib
import re
import time
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING

import typer

from rtsgt.errors import InputError

if TYPE_CHECKING:
    from rtsgt.cli.tables import TextTable
    from rtsgt.record import PositionRunRecord, RunRecord


def usage_error(message: str, option: str) -> typer.BadParameter:
    """A bad value of a command-line option, for ``raise`` (exit status 2)."""
    if message[:1].isupper() and message[1:2].islower():  # "Expected ..." -> "expected ..."
        message = message[0].lower() + message[1:]
    return typer.BadParameter(message, param_hint=option)


def checked_options(build: Callable[..., object], names: dict[str, str], **values) -> dict:
    """The given (not None) values, each checked by ``build``'s rule (the configuration's); a
    bad one is a usage error naming its option (``names``: field -> option)."""
    changes = {k: v for k, v in values.items() if v is not None}
    for key, value in changes.items():
        try:
            build(**{key: value})
        except InputError as exc:
            raise usage_error(exc.bare_message, names[key]) from None
    return changes


@contextlib.contextmanager
def collected_warnings():
    """Collect a command's warnings (for :func:`print_warnings`) instead of printing them."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield caught


#: A warning longer than this (characters) is shortened in the terminal to its first clause.
SHORT_WARNING = 160


def warning_groups(messages: list[str]) -> list[tuple[str, list[str]]]:
    """Warnings grouped by topic, ``(topic, subjects)`` in order of first warning; a group of
    one is the warning itself, shortened beyond :data:`SHORT_WARNING`
    (docs/cli.md#errors-warnings-and-exit-statuses)."""
    groups: dict[str, list[tuple[str, str]]] = {}
    for message in messages:
        topic, _, detail = message.partition(": ")
        bare = re.sub(r"\s*\([^)]*\)", "", topic).strip()
        key = re.split(r" (?:of|over|for) ", bare, maxsplit=1)[0]
        subject = bare[len(key):].strip()
        subject = re.sub(r"^(?:of|over|for) ", "", subject)
        if not subject:
            head = re.sub(r"\s*\([^)]*\)", "", detail.partition(": ")[0]).strip()
            subject = head if len(head) <= 30 and ":" in detail else ""
        groups.setdefault(key, []).append((message, subject))
    out = []
    for key, items in groups.items():
        if len(items) == 1:
            message = items[0][0]
            if len(message) > SHORT_WARNING:
                message = _first_clause(message)
            out.append((message, []))
        else:
            out.append((key, [subject for _, subject in items]))
    return out


def _first_clause(message: str) -> str:
    """``message`` up to its first ``"; "`` outside parentheses and brackets (whole if none)."""
    depth = 0
    for i, ch in enumerate(message):
        depth += (ch in "([") - (ch in ")]")
        if depth == 0 and message.startswith("; ", i):
            return message[:i]
    return message


def print_warnings(caught, where) -> None:
    """The collected warnings on stderr, one line per group, and where their whole text is
    (``where``; None: the command failed, each warning whole)."""
    messages = [" ".join(str(w.message).split()) for w in caught]
    if not messages:
        return
    if where is None:
        for message in messages:
            echo_err(f"warning: {message}")
        return
    for text, subjects in warning_groups(messages):
        named = [s for s in subjects if s]
        if subjects:
            text += f" ({len(subjects)} warnings" + (f": {', '.join(named)}" if named else "") + ")"
        echo_err(f"warning: {text}")
    echo_err(f"(the whole text of {len(messages)} warning{'s' if len(messages) > 1 else ''}: "
             f"{where})")


def echo_err(msg: str) -> None:
    """A line on stderr."""
    typer.echo(msg, err=True)


class Stages:
    """A progress display on stderr: call it with each stage's name as the stage starts."""

    def __init__(self, quiet: bool = False):
        from rich.console import Console

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
    """A short key-value table of what a run produced and what its self-checks found."""
    import numpy as np
    from rich.console import Console

    from rtsgt.cli.tables import TextTable
    from rtsgt.record import MIN_POSE_PRISMS, PositionRunRecord

    table = TextTable(f"rtsgt run: {record.name}", ("", ""), header=False, right=(False, False))
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
        table.add_row("median sigma (sqrt trace)",
                      f"{np.median(sig_t):.2f} mm translation, {np.median(sig_r):.3f} mrad "
                      "rotation")
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
    _calibration_rows(table, record)
    _ratio_rows(table, "self-check z^2", ("poses", "poses"), "mean_z2",
                record.self_checks.get("inter_prism_distances", {}))
    _ratio_rows(table, "self-check block CV", ("blocks", "windows"), "nees_per_dof",
                record.self_checks.get("block_cv", {}))
    _static_rows(table, record.self_checks.get("static_noise", {}), record.correlated_noise)
    _structure_rows(table, record.self_checks.get("inter_prism_structure", {}))
    table.add_row("output", str(out))
    table.print(Console())


def _ratio(v: dict, key: str) -> str:
    """``value [lo, hi] verdict`` of a check with a 95 % interval."""
    lo, hi = v["interval_95"]
    return f"{v[key]:.2f} [{lo:.2f}, {hi:.2f}] {v['verdict']}"


def _ratio_rows(table: TextTable, name: str, count: tuple[str, str], key: str,
                check: dict) -> None:
    """A check of the whole run and its regimes (95 % intervals): one row for the whole run
    (``count``: the key of its sample count and its unit in words), one for the regimes."""
    overall = check.get("overall")
    if overall and overall.get("interval_95"):
        table.add_row(f"{name}, whole run ({overall[count[0]]} {count[1]})", _ratio(overall, key))
    regimes = [f"{k} {_ratio(v, key)}" for k, v in check.get("regimes", {}).items()
               if v and v.get("interval_95")]
    if regimes:
        table.add_row(f"{name}, by regime", "; ".join(regimes))


def _calibration_rows(table: TextTable, record) -> None:
    """The calibration's model, method and self-checks."""
    from rtsgt.calibration.result import (
        CALIBRATION_METHOD_NAMES,
        CALIBRATION_MODEL_NAMES,
        CALIBRATION_WEIGHTING_NAMES,
    )

    gcp = record.self_checks.get("gcp_fit", {})
    if gcp.get("model"):
        table.add_row("calibration model", CALIBRATION_MODEL_NAMES[gcp["model"]]
                      + (f"; {CALIBRATION_WEIGHTING_NAMES[gcp['weighting']]}"
                         if gcp.get("weighting") else ""))
    table.add_row("calibration method", CALIBRATION_METHOD_NAMES[record.options.calibration.method])
    dyn = record.self_checks.get("dynamic_calibration")
    if dyn:
        lo, hi = dyn["interval_95"]
        table.add_row(f"self-check {dyn['method']} calibration ({dyn['samples']} samples)",
                      f"{dyn['variance_factor']:.2f} [{lo:.2f}, {hi:.2f}] {dyn['verdict']}")
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
                          f"variance factor {v['variance_factor']:.2f} [{lo:.2f}, {hi:.2f}] "
                          f"{v['verdict']}")
    added = gcp.get("added_shot_sigma_mm", {})
    if any(added.values()):
        table.add_row("calibration: added per shot", f"{added['horizontal']:.2f} mm horizontal, "
                      f"{added['vertical']:.2f} mm vertical")


def _static_rows(table: TextTable, static: dict, plan: dict) -> None:
    """The static stretches' noise per prism, and whether the correlated part was inflated."""
    if static and not static.get("prisms"):
        table.add_row("self-check static", static.get("note", "no static stretch"))
    for pid, e in static.get("prisms", {}).items():
        parts, taus = [], []
        for name in ("range", "horizontal", "vertical"):
            c = e[name]
            lv, co = c["level"], c["correlation"]
            parts.append(f"{name} {c['observed_sigma_mm']:.2f} / {c['predicted_sigma_mm']:.2f} "
                         f"mm {lv['verdict']}")
            if co.get("verdict") == "optimistic" and co.get("correlation_time_s") is not None:
                taus.append(f"{name} {co['correlation_time_s']:.1f} s")
        text = f"{e['samples']} samples; scatter / predicted: " + ", ".join(parts)
        if taus:
            text += "; correlated: " + ", ".join(taus)
        table.add_row(f"self-check static, prism {pid}", text)
    for pid, e in plan.get("prisms", {}).items():
        found = [(name, e[name]) for name in ("range", "horizontal", "vertical")
                 if e[name].get("rho") is not None]
        if found:
            done = any(c["applied"] for _, c in found)
            table.add_row(f"correlated noise, prism {pid}",
                          f"white variance {'inflated' if done else 'not inflated (ignore)'}: "
                          + ", ".join(f"{name} x{c['factor']:.1f}" for name, c in found))


def _structure_rows(table: TextTable, check: dict) -> None:
    """The inter-prism residual structure check (:mod:`rtsgt.checks.structure`)."""
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
            f"{k}: {v['run']:+.2f} ± {v['sigma']:.2f} ms" for k, v in offsets.items()))
