"""The table across the deployments of ``rtsgt batch``: one row per deployment, as CSV
(:data:`BATCH_COLUMNS`), every number and verdict read back from the run's ``summary.json``
(:func:`rtsgt.io.run_dir.read_summary`), never recomputed. docs/batch.md#output.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Mapping
from os import PathLike

from rtsgt.errors import InputError
from rtsgt.io._parse import atomic_write_text
from rtsgt.io.run_dir import read_summary
from rtsgt.stats import VERDICTS

BATCH_COLUMNS = (
    "deployment", "status", "seed", "elapsed_s", "poses_queried", "poses_kept",
    "rejected_distance", "rejected_uncertainty", "rejected_degenerate",
    "median_sigma_translation_mm", "median_sigma_rotation_mrad", "check_gcp_fit",
    "check_inter_prism_distances", "check_block_cv", "check_clock", "check_prism_orientation",
    "check_static_noise", "warnings", "run_dir", "config", "error",
)
#: The columns of the self-checks' verdicts.
CHECK_COLUMNS = tuple(c for c in BATCH_COLUMNS if c.startswith("check_"))


def _grouped(parts: Iterable[tuple[str, str]]) -> str:
    """``consistent`` when every tested part is, else each failing verdict (pessimistic,
    optimistic) with its parts; when no part was tested, what the check says (e.g. ``too
    few poses``)."""
    parts = [(name, v) for name, v in parts if v]
    failing: dict[str, list[str]] = {}
    for name, v in parts:
        if v in VERDICTS[1:]:
            failing.setdefault(v, []).append(name)
    if failing:
        return "; ".join(f"{v} ({', '.join(names)})" for v, names in sorted(failing.items()))
    if any(v == VERDICTS[0] for _, v in parts):
        return VERDICTS[0]
    return parts[0][1] if parts else ""


def _regimes(check: Mapping) -> str:
    overall = check.get("overall") or {}
    parts = [("whole run", overall.get("verdict", ""))]
    parts += [(k, (v or {}).get("verdict", "")) for k, v in (check.get("regimes") or {}).items()]
    return _grouped(parts)


def check_verdicts(checks: Mapping) -> dict[str, str]:
    """The ``check_*`` columns of a run's ``self_checks`` (module docstring)."""
    out = dict.fromkeys(CHECK_COLUMNS, "")
    gcp = checks.get("gcp_fit") or {}
    out["check_gcp_fit"] = _grouped((str(s), v.get("verdict", ""))
                                    for s, v in (gcp.get("stations") or {}).items()
                                    if v.get("dof"))
    if checks.get("inter_prism_distances"):
        out["check_inter_prism_distances"] = _regimes(checks["inter_prism_distances"])
    if checks.get("block_cv"):
        out["check_block_cv"] = _regimes(checks["block_cv"])
    structure = checks.get("inter_prism_structure") or {}
    for key in ("clock", "prism_orientation"):
        out[f"check_{key}"] = str((structure.get(key) or {}).get("verdict") or "")
    static = checks.get("static_noise") or {}
    verdicts = [e[comp][test].get("verdict", "")
                for e in (static.get("prisms") or {}).values()
                for comp in ("range", "horizontal", "vertical") if comp in e
                for test in ("level", "correlation") if test in e[comp]]
    tested = [v for v in verdicts if v in VERDICTS]
    if tested:
        bad = {v: tested.count(v) for v in VERDICTS[1:] if v in tested}
        out["check_static_noise"] = (
            VERDICTS[0] if not bad
            else ", ".join(f"{v} {n}" for v, n in bad.items()) + f" of {len(tested)}")
    elif verdicts:
        out["check_static_noise"] = verdicts[0]
    return out


def batch_row(name: str, status: str, seed: int, run_dir: str | PathLike,
              config: str | PathLike, *, elapsed_s: float | None = None,
              error: str = "") -> dict[str, object]:
    """One row of the table: the deployment's ``summary.json`` read back (none for a failed
    deployment; an unreadable summary is said in ``error``)."""
    row: dict[str, object] = dict.fromkeys(BATCH_COLUMNS, "")
    row.update(deployment=name, status=status, seed=seed, run_dir=str(run_dir),
               config=str(config), error=error)
    if elapsed_s is not None and status == "done":
        row["elapsed_s"] = round(float(elapsed_s), 3)
    if status == "failed":
        return row
    try:
        summary = read_summary(run_dir)
    except InputError as exc:
        row["error"] = f"summary.json unreadable: {exc}"
        return row
    doc = summary.document
    poses = doc.get("poses") or {}
    rejected = (doc.get("gates") or {}).get("rejected_by") or {}
    sigma = doc.get("median_uncertainty") or {}
    row.update(
        poses_queried=poses.get("queried", ""), poses_kept=poses.get("kept", ""),
        rejected_distance=rejected.get("distance", ""),
        rejected_uncertainty=rejected.get("uncertainty", ""),
        rejected_degenerate=rejected.get("degenerate", ""),
        median_sigma_translation_mm=_num(sigma.get("translation_mm")),
        median_sigma_rotation_mrad=_num(sigma.get("rotation_mrad")),
        warnings=len(summary.warnings),
    )
    row.update(check_verdicts(summary.self_checks))
    return row


def _num(x) -> object:
    return "" if x is None else float(x)


def batch_csv_text(rows: Iterable[Mapping]) -> str:
    """The CSV of the rows: a header of :data:`BATCH_COLUMNS`, one line per deployment
    (floats in their shortest exact form)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(BATCH_COLUMNS)
    for row in rows:
        w.writerow([repr(v) if isinstance(v, float) else v for v in
                    (row.get(c, "") for c in BATCH_COLUMNS)])
    return buf.getvalue()


def write_batch_csv(path: str | PathLike, rows: Iterable[Mapping]) -> None:
    """Write :func:`batch_csv_text` atomically."""
    atomic_write_text(path, batch_csv_text(rows))
