"""``rtsgt batch``: the ground truth of many deployments, on Dask or one after the other.

Over :mod:`rtsgt.batch` and :mod:`rtsgt.io.batch_summary` / :mod:`rtsgt.report.batch`: a
progress bar, one ``failed: NAME: message`` line per failed deployment, the table and
``OUT/batch_summary.{csv,html}``; Ctrl-C: docs/cli.md#start-up-interrupts-threads-and-help;
failures: docs/batch.md#failures.
"""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.cli.common import usage_error
from rtsgt.cli.run import option_overrides
from rtsgt.errors import InputError
from rtsgt.io.output_dir import open_output_folder, record_files

if TYPE_CHECKING:
    from rich.progress import Progress

    from rtsgt.batch import Outcome

#: The files the batch writes into its output folder, beside the run directories.
SUMMARY_CSV, SUMMARY_HTML = "batch_summary.csv", "batch_summary.html"


def run_batch(
    inputs: list[Path], out: Path, *, seed: int = 0, workers: int | None = None,
    scheduler: str | None = None, serial: bool = False, force: bool = False,
    quiet: bool = False, report: bool = False, **run_options,
) -> tuple[list[Outcome], list[dict], Path]:
    """Run every deployment under ``inputs`` into ``out``; returns the outcomes, the summary
    rows and the output folder. ``run_options``: ``rtsgt run``'s (``engine``, ``rate``, ...).
    A bad option is a usage error; a failed deployment an InputError after the others."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from rtsgt.batch import find_deployments, make_tasks
    from rtsgt.batch import run_batch as run_tasks

    if serial and (workers is not None or scheduler is not None):
        raise usage_error("runs in this process: leave out --workers and --scheduler", "--serial")
    if workers is not None and scheduler is not None:
        raise usage_error("an existing cluster has its own workers: leave out --workers",
                          "--scheduler")
    given = {k: v for k, v in run_options.items() if v is not None}
    option_overrides(**{{"rate": "rate_hz"}.get(k, k): v for k, v in given.items()})
    deployments, notes = find_deployments(inputs, out=out)
    folder = open_output_folder(out, "batch")
    tasks = make_tasks(deployments, folder, base_seed=seed, options=given, force=force,
                       report=report)
    err = Console(stderr=True)
    for note in notes:
        err.print(f"note: {note}", highlight=False, markup=False, soft_wrap=True)

    where = {"ran": "serially, in this process"}
    t0 = time.perf_counter()
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TimeElapsedColumn(), TimeRemainingColumn(), console=err, disable=quiet)
    with progress, _quiet_interrupt(progress):
        bar = progress.add_task("deployments", total=len(tasks))

        def on_outcome(o: Outcome) -> None:
            if o.status == "failed":
                progress.console.print(f"failed: {o.name}: {o.message}", highlight=False,
                                       markup=False, soft_wrap=True)
            progress.advance(bar)

        factory = None if serial else _client_factory(workers, scheduler, where)
        outcomes = run_tasks(tasks, client_factory=factory, on_outcome=on_outcome)
    wall = time.perf_counter() - t0
    rows, info = _write_summary(outcomes, folder, seed, where["ran"], wall)
    if not quiet:
        _print_table(rows, folder, info)
    if info["failed"]:
        raise InputError(f"{info['failed']} of {len(outcomes)} deployments failed (the "
                         f"'failed:' lines above); the others' runs and the summary are in "
                         f"{folder}")
    return outcomes, rows, folder


def _client_factory(workers: int | None, scheduler: str | None, where: dict):
    """The batch's Dask client factory (``n_todo -> client``); says in ``where`` where it ran."""
    from rtsgt.batch import dask_client, default_workers

    def client_factory(n_todo: int):
        if scheduler is not None:
            where["ran"] = f"on the Dask scheduler {scheduler}"
            return dask_client(scheduler=scheduler, n_tasks=n_todo)
        n = workers if workers is not None else default_workers(n_todo)
        where["ran"] = f"on a local Dask cluster of {n} worker process{'es' * (n > 1)}"
        try:  # distributed first: its defaults are in dask's configuration once imported
            import distributed  # noqa: F401
            from dask import config
        except ImportError:  # dask_client says how to install it
            return dask_client(workers=workers, n_tasks=n_todo)
        # Ctrl-C stops the batch, not the workers: they start with SIGINT ignored, then
        # run dask_setup below
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            with config.set({"distributed.worker.preload": [__name__]}):
                return dask_client(workers=workers, n_tasks=n_todo)
        finally:
            signal.signal(signal.SIGINT, previous)

    return client_factory


def _write_summary(outcomes: list[Outcome], folder: Path, seed: int, ran: str,
                   wall: float) -> tuple[list[dict], dict]:
    """Write ``batch_summary.csv`` and ``.html`` into ``folder``; returns its rows and info."""
    from rtsgt.io.batch_summary import batch_row, write_batch_csv
    from rtsgt.report.batch import write_batch_html

    rows = [batch_row(o.name, o.status, o.seed, o.out, o.config, elapsed_s=o.elapsed_s,
                      error=o.message) for o in outcomes]
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    info = {"deployments": len(outcomes), "run now": counts["done"],
            "skipped (complete)": counts["skipped"], "failed": counts["failed"],
            "base seed": seed, "ran": ran if counts["done"] + counts["failed"]
            else "nothing to run", "wall time": f"{wall:.1f} s"}
    write_batch_csv(folder / SUMMARY_CSV, rows)
    write_batch_html(folder / SUMMARY_HTML, rows, info)
    record_files(folder, [folder / SUMMARY_CSV, folder / SUMMARY_HTML])
    return rows, info


@contextlib.contextmanager
def _quiet_interrupt(progress: Progress):
    """Ctrl-C while the batch runs: the progress bar off the screen, Dask's log silenced."""
    def handler(signum, frame):
        if progress.console.is_terminal:
            progress.live.transient = True
        else:  # a file or a pipe: not even the newline of a transient display
            progress.console.quiet = True
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        signal.default_int_handler(signum, frame)

    try:
        previous = signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread: nothing to take over
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def dask_setup(worker) -> None:
    """Dask's preload hook of each local worker: Ctrl-C only silences the worker's log."""
    def silence(signum, frame):
        logging.getLogger("distributed").setLevel(logging.CRITICAL)

    signal.signal(signal.SIGINT, silence)


def _print_table(rows: list[dict], folder: Path, info: dict) -> None:
    from rich.console import Console

    from rtsgt.cli.tables import TextTable
    from rtsgt.io.batch_summary import CHECK_COLUMNS
    from rtsgt.stats import VERDICTS

    table = TextTable(f"rtsgt batch: {len(rows)} deployments, {info['run now']} run now, "
                      f"{info['skipped (complete)']} complete already, {info['failed']} "
                      f"failed ({info['ran']}, {info['wall time']})",
                      ("deployment", "status", "poses kept / queried", "sigma mm",
                       "sigma mrad", "checks failed", "warnings"),
                      right=(False, False, True, True, True, True, True))
    for r in rows:
        # the self-checks with a pessimistic or optimistic part, of those that tested any
        failing = sum(any(v in str(r[c]) for v in VERDICTS[1:]) for c in CHECK_COLUMNS)
        tested = sum(any(v in str(r[c]) for v in VERDICTS) for c in CHECK_COLUMNS)
        table.add_row(
            str(r["deployment"]), str(r["status"]),
            f"{r['poses_kept']} / {r['poses_queried']}" if r["poses_kept"] != "" else "",
            _fmt(r["median_sigma_translation_mm"], 2), _fmt(r["median_sigma_rotation_mrad"], 3),
            f"{failing} of {tested}" if tested else "", str(r["warnings"]))
    console = Console()
    table.print(console)
    console.print(f"summary: {folder / SUMMARY_CSV}, {folder / SUMMARY_HTML}", highlight=False)


def _fmt(x, digits: int) -> str:
    return f"{x:.{digits}f}" if isinstance(x, float) and math.isfinite(x) else ""


def register(app: typer.Typer) -> None:
    """Add ``rtsgt batch`` to the application."""

    @app.command("batch")
    def batch_command(
        inputs: list[Path] = typer.Argument(
            ..., metavar="DEPLOYMENTS...",
            help="Deployment TOML files, deployment folders (holding deployment.toml), or "
                 "folders of them."),
        out: Path = typer.Option(Path("rtsgt-batch"), "--out", "-o",
                                 help="Output folder: one run directory per deployment and "
                                      "the summary (CSV, HTML)."),
        seed: int = typer.Option(0, min=0, help="Base seed; each deployment's seed is derived "
                                                "from it and the deployment's name (>= 0)."),
        workers: int = typer.Option(None, "--workers", min=1,
                                    help="Worker processes of the local Dask cluster (default: "
                                         "sized to the machine)."),
        scheduler: str = typer.Option(None, "--scheduler", metavar="ADDRESS",
                                      help="An existing Dask cluster's scheduler, e.g. "
                                           "tcp://host:8786 (its workers need rtsgt)."),
        serial: bool = typer.Option(False, "--serial",
                                    help="One deployment after the other in this process "
                                         "(no Dask; for debugging)."),
        force: bool = typer.Option(False, "--force",
                                   help="Run every deployment again, complete or not "
                                   "(replacing run directories rtsgt wrote, nothing " "else)."),
        engine: str = typer.Option(None, help="Pose engine: mc, ut or linear (default: each "
                                              "deployment's config)."),
        registration: str = typer.Option(None, help="weighted or unweighted (default: " "config)."),
        samples: int = typer.Option(None, help="Monte Carlo samples M (default: config)."),
        rate: float = typer.Option(None, help="Query rate, Hz (default: config)."),
        prior: str = typer.Option(None, help="GP motion prior: wnoa, wnoj or select "
                                             "(default: config)."),
        correlated_noise: str = typer.Option(None, "--correlated-noise",
                                             help="inflate or ignore (default: config)."),
        profile: str = typer.Option(None, help="Preset of the switches: paper (a switch "
                                               "given with it wins) (default: config)."),
        report: bool = typer.Option(False, "--report", help="Also write each run's HTML report."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress, no table."),
    ) -> None:
        """Compute the ground truth of many deployments (resumable; on Dask by default)."""
        run_batch(inputs, out, seed=seed, workers=workers, scheduler=scheduler, serial=serial,
                  force=force, quiet=quiet, report=report, engine=engine,
                  registration=registration, samples=samples, rate=rate, prior=prior,
                  correlated_noise=correlated_noise, profile=profile)
