"""The drift table of ``rtsgt evaluate`` (CLI edge): drift by segment length with the ground
truth's floor (:mod:`rtsgt.evaluation.drift`, docs/evaluating.md#drift-by-segment-length),
from the ``drift`` section of the JSON layout, so that the table shows what ``--json`` gives.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rtsgt.cli.tables import TextTable

if TYPE_CHECKING:
    from rich.console import Console

#: (kind, unit of the lengths, translation key and unit shown, its scale from the JSON,
#: rotation key and unit shown).
_KINDS = (
    ("distance", "m", "pct", "%", 1.0, "deg_per_m", "deg/m"),
    ("time", "s", "m_per_s", "mm/s", 1e3, "deg_per_s", "deg/s"),
)


def _cell(value: float | None, floor: float | None, unit: str, scale: float = 1.0) -> str:
    if value is None:
        return "-"
    text = f"{scale * value:.3g} {unit}"
    return text + (" (<= floor)" if floor is not None and value <= floor else "")


def _rows(table: TextTable, sec: dict, kind: tuple) -> None:
    """The rows of one kind of segment: each length, then all pooled."""
    _, lu, tk, tu, ts, rk, ru = kind
    entries = [(f"{r[f'length_{lu}']:g} {lu}", r) for r in sec["by_length"]]
    lengths = sec[f"lengths_{lu}"]
    entries.append((f"all, {lengths[0]:g}-{lengths[-1]:g} {lu}",
                    {**sec, "n": sec["n_segments"]}))
    for name, r in entries:
        t, tf = r[f"translation_{tk}"], r[f"translation_floor_{tk}"]
        rot, rf = r[f"rotation_{rk}"], r[f"rotation_floor_{rk}"]
        table.add_row(name, str(r["n"]), _cell(t, tf, tu, ts),
                      "-" if tf is None else f"{ts * tf:.3g} {tu}",
                      _cell(rot, rf, ru), "-" if rf is None else f"{rf:.3g} {ru}")


def print_drift(drift: dict | None, console: Console) -> None:
    """The drift table of the ``drift`` section of the JSON (None: nothing printed)."""
    if drift is None or (drift["distance"] is None and drift["time"] is None):
        return
    table = TextTable("Drift by segment length (KITTI devkit definition: mean over segments "
                      "every 10 poses; floor: the ground truth's own, rms)",
                      ("segment", "n", "translation", "floor", "rotation", "floor"))
    first = True
    for kind in _KINDS:
        sec = drift[kind[0]]
        if sec is None:
            continue
        if not first:
            table.add_section()
        first = False
        _rows(table, sec, kind)
    table.print(console)
    d = drift["distance"]
    notes = [] if d is None else [f"lengths of path: {d['lengths_from']}"]
    notes.append("rotation per metre as the devkit (KITTI's leaderboard shows deg/100 m); "
                 "'<= floor': not resolved by this ground truth")
    if drift["rotation"]:
        notes.append(f"rotational drift {drift['rotation']}")
    console.print("; ".join(notes), highlight=False)
