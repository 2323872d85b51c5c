"""The HTML page of ``rtsgt batch``: the table across deployments (the rows of
:mod:`rtsgt.io.batch_summary`), each linking to its run's ``report.html`` or ``summary.json``,
verdicts coloured. One self-contained file. docs/batch.md#output.
"""

from __future__ import annotations

import html
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from rtsgt import __version__
from rtsgt.io._parse import atomic_write_text
from rtsgt.io.batch_summary import BATCH_COLUMNS, CHECK_COLUMNS
from rtsgt.report.style import CSS
from rtsgt.stats import VERDICTS

#: Column headers of the page (the CSV's names, shorter).
_HEADERS = {
    "deployment": "deployment", "status": "status", "seed": "seed", "elapsed_s": "time, s",
    "poses_queried": "poses queried", "poses_kept": "kept",
    "rejected_distance": "rejected: distance", "rejected_uncertainty": "uncertainty",
    "rejected_degenerate": "degenerate",
    "median_sigma_translation_mm": "median σ, mm", "median_sigma_rotation_mrad": "median σ, mrad",
    "check_gcp_fit": "GCP fit", "check_inter_prism_distances": "inter-prism distances",
    "check_block_cv": "block CV", "check_clock": "clock offsets",
    "check_prism_orientation": "prism orientation", "check_static_noise": "static noise",
    "warnings": "warnings", "error": "error",
}
_COLOURS = {VERDICTS[0]: "#e3f4e1", VERDICTS[1]: "#fff1cc", VERDICTS[2]: "#fbe0de",
            "failed": "#fbe0de"}
_BATCH_CSS = ("td.v{text-align:left;font-size:.92em}td.err{text-align:left;color:#900;"
              "max-width:30em}")


def _cell(col: str, value: object) -> str:
    text = "" if value is None else (f"{value:.3g}" if isinstance(value, float) else str(value))
    if col in CHECK_COLUMNS:
        # green when consistent, red when a part is optimistic, amber when one is
        # pessimistic; none when nothing could be tested
        colour = next((_COLOURS[v] for v in (VERDICTS[2], VERDICTS[1]) if v in text),
                      _COLOURS[VERDICTS[0]] if text == VERDICTS[0] else None)
        style = f" style='background:{colour}'" if colour else ""
        return f"<td class='v'{style}>{html.escape(text)}</td>"
    if col == "error":
        return f"<td class='err'>{html.escape(text)}</td>"
    if col == "status":
        style = f" style='background:{_COLOURS['failed']}'" if text == "failed" else ""
        return f"<td class='s'{style}>{html.escape(text)}</td>"
    return f"<td>{html.escape(text)}</td>"


def _link(row: Mapping, page_dir: Path) -> str:
    name = html.escape(str(row["deployment"]))
    run = Path(str(row.get("run_dir", "")))
    for target in (run / "report.html", run / "summary.json"):
        if row.get("status") != "failed" and target.is_file():
            href = Path(os.path.relpath(target, page_dir)).as_posix()
            return f"<td class='k'><a href='{html.escape(href)}'>{name}</a></td>"
    return f"<td class='k'>{name}</td>"


def batch_html(rows: Sequence[Mapping], *, path: str | os.PathLike, info: Mapping) -> str:
    """The page of ``rows`` to be written at ``path`` (links are relative to it); ``info``:
    what the batch was (base seed, where it ran, counts), shown above the table."""
    page_dir = Path(os.path.abspath(path)).parent
    cols = [c for c in BATCH_COLUMNS if c in _HEADERS]
    head = "".join(f"<th{' class=k' if c == 'deployment' else ''}>{html.escape(_HEADERS[c])}"
                   "</th>" for c in cols)
    body = "".join(
        "<tr>" + "".join(_link(r, page_dir) if c == "deployment" else _cell(c, r.get(c))
                         for c in cols) + "</tr>"
        for r in rows)
    facts = "".join(f"<div>{html.escape(str(k))}<b>{html.escape(str(v))}</b></div>"
                    for k, v in info.items())
    title = f"rtsgt batch: {page_dir.name}"
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{html.escape(title)}</title><style>{CSS}{_BATCH_CSS}</style></head><body>"
        f"<main><h1>{html.escape(title)}</h1><div class='kpi'>{facts}</div>"
        f"<table id='batch'><tr>{head}</tr>{body}</table>"
        "<p><small>Every value is read from the deployment's summary.json. σ: the median over "
        "the kept poses of the square root of the trace of the position (rotation) block. "
        "Verdicts of the self-checks: consistent when every part is, else each failing "
        "verdict with its stations or regimes (rtsgt's docs/self-checks.md); the static "
        "stretches as counts of tests. The same table: batch_summary.csv. "
        f"rtsgt {html.escape(__version__)}.</small></p></main></body></html>\n")


def write_batch_html(path: str | os.PathLike, rows: Sequence[Mapping], info: Mapping) -> None:
    """Write :func:`batch_html` atomically."""
    atomic_write_text(path, batch_html(rows, path=path, info=info))
