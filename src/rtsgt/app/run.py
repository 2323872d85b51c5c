"""The use case "compute the ground truth of a deployment": read it, run the pipeline, write
the run directory (docs/architecture.md#layers).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from rtsgt.errors import RtsgtWarning
from rtsgt.io.deployment import load_deployment, resolve_config
from rtsgt.io.output_dir import check_target
from rtsgt.io.run_dir import write_run
from rtsgt.options import RunOptions
from rtsgt.pipeline import run_pipeline
from rtsgt.record import PositionRunRecord, RunRecord

__all__ = ["DeploymentRun", "run_deployment"]


@dataclass(frozen=True)
class DeploymentRun:
    """What :func:`run_deployment` produced: the run's ``record`` and its run directory
    ``path`` (``summary.json`` in it; ``report.html`` too when ``report`` is not None)."""

    record: RunRecord | PositionRunRecord
    path: Path
    report: Path | None = None

    @property
    def summary(self) -> Path:
        """The run's ``summary.json``."""
        return self.path / "summary.json"


def run_deployment(
    config: str | Path, out: str | Path, *, options: Mapping[str, object] | None = None,
    profile: str | None = None, seed: int = 0, force: bool = False, report: bool = False,
    inputs: dict | None = None, progress: Callable[[str], None] | None = None,
) -> DeploymentRun:
    """Read the deployment ``config`` (a TOML or its folder), run the pipeline and write its
    run directory at ``out`` atomically. ``options``: flat names of
    :meth:`rtsgt.options.RunOptions.updated`, over ``profile``'s switches, checked (with
    ``out``) before any work; ``report`` adds the HTML report (poses only); ``inputs``: what
    ``summary.json`` records (default: the config's path); ``progress(stage name)``."""
    say = progress if progress is not None else _silent
    changes = dict(options or {})
    RunOptions().updated(profile=profile, **changes)  # a bad value: InputError, before any work
    config = resolve_config(config)
    check_target(out, force=force, inputs=[config])
    say("reading inputs")
    data, read = load_deployment(config)
    record = run_pipeline(data, read.updated(profile=profile, seed=seed, **changes), progress=say)
    say("writing outputs")
    if report and isinstance(record, PositionRunRecord):
        warnings.warn("--report: the HTML report is of runs with poses; this run gives "
                      "positions only (prisms/prism<i>.csv), and no report is written",
                      RtsgtWarning, stacklevel=2)
        report = False

    def add_report(tmp: Path, final: Path) -> None:
        # matplotlib only for a report: `rtsgt run` starts without it (docs/architecture.md#layers)
        from rtsgt.report.html import write_report

        say("analysis, figures and HTML report")
        write_report(tmp, shown_path=final)

    if inputs is None:
        inputs = {"config": str(Path(config).resolve())}
    final = write_run(record, out, force=force, inputs=inputs, protect=[config],
                      finish=add_report if report else None)
    return DeploymentRun(record, final, final / "report.html" if report else None)


def _silent(stage: str) -> None:
    """No progress display."""
