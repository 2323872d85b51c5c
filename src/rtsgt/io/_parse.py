"""Shared helpers of the readers and writers: line-numbered parsing, validation, atomic writes.

Bad input is an :class:`~rtsgt.errors.InputError` naming the file and the 1-based line;
writers write a temporary file beside the destination and :func:`os.replace` it. Blank and
``#`` lines are ignored, except in a run directory's tables (:func:`read_table`). Times are
seconds: one reaching :data:`MAX_SECONDS` is refused by :func:`check_seconds`, saying which
unit it looks like; rtsgt never guesses a unit.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from datetime import datetime, timezone
from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt.errors import InputError

#: Encodings tried in turn when decoding a text file (ECCC files exist in both).
ENCODINGS = ("utf-8-sig", "cp1252")


def read_text(path: str | PathLike, encodings: Sequence[str] = ENCODINGS) -> str:
    """Whole text of a file, UTF-8 (with or without BOM) or Windows-1252.

    Parameters
    ----------
    path : str or PathLike
    encodings : sequence of str
        Encodings tried in turn (default :data:`ENCODINGS`).

    Raises
    ------
    InputError
        The file does not exist, is a directory, cannot be read or decoded.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("file not found", p)
    if p.is_dir():
        raise InputError("expected a file, got a directory", p)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror})", p) from exc
    for enc in encodings:
        try:
            return raw.decode(enc)
        except UnicodeDecodeError:
            continue
    raise InputError(f"cannot decode the file as {' or '.join(encodings)} text", p)


def numbered_lines(text: str) -> tuple[list[int], list[str]]:
    """1-based numbers and contents of the lines that are neither blank nor ``#`` comments."""
    numbers: list[int] = []
    lines: list[str] = []
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            numbers.append(i)
            lines.append(s)
    return numbers, lines


def is_number(token: str) -> bool:
    """Whether ``token`` reads as a number (a header's first cell does not)."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def ns_to_seconds(ns: np.ndarray) -> np.ndarray:
    """Integer nanoseconds to float seconds without losing the sub-second part."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(float) + (ns % 1_000_000_000).astype(float) * 1e-9


def read_lines(path: str | PathLike, what: str) -> tuple[list[int], list[str]]:
    """Numbered non-blank, non-comment lines of a file; :class:`InputError` if there are none.

    Parameters
    ----------
    path : str or PathLike
    what : str
        What the file should hold, for the message ("tracked prism measurements").
    """
    numbers, lines = numbered_lines(read_text(path))
    if not lines:
        raise InputError(f"empty file: expected {what}, found no data line", path)
    return numbers, lines


def split_rows(
    lines: Sequence[str],
    numbers: Sequence[int],
    path: str | PathLike,
    columns: Sequence[str],
    sep: str | None,
) -> np.ndarray:
    """Split lines into a (N, K) array of stripped tokens, checking the column count.

    Parameters
    ----------
    lines, numbers : sequences of length N
        Line contents and their 1-based line numbers.
    path : str or PathLike
        File name for messages.
    columns : sequence of str, length K
        Expected column names (for messages).
    sep : str or None
        Separator (``None``: any run of whitespace).
    """
    k = len(columns)
    rows = [line.split(sep) for line in lines]
    for row, number in zip(rows, numbers, strict=True):
        if len(row) != k:
            how = "whitespace-separated" if sep is None else f"{sep.strip() or repr(sep)}-separated"
            raise InputError(
                f"expected {k} {how} columns ({' '.join(columns)}), got {len(row)}", path, number
            )
    out = np.array(rows, dtype=object).reshape(len(rows), k)
    return np.vectorize(str.strip, otypes=[object])(out) if out.size else out


def to_float(
    tokens: np.ndarray,
    numbers: Sequence[int],
    path: str | PathLike,
    names: Sequence[str],
    *,
    finite: bool | np.ndarray = True,
    decimal_comma: bool = False,
) -> np.ndarray:
    """``tokens`` (N, K) as float64, a bad token naming its line (``numbers``, 1-based) and column
    (``names``) of ``path``; ``finite`` rejects NaN and infinities (all rows or a row mask);
    ``decimal_comma`` reads ``"93,44"`` as 93.44 (the whole field)."""
    tok = np.asarray(tokens, dtype=object)
    if decimal_comma:
        tok = np.vectorize(lambda s: s.replace(",", "."), otypes=[object])(tok) if tok.size else tok
    try:
        out = tok.astype(float)
    except ValueError:
        for i, j in np.ndindex(*tok.shape):
            try:
                float(tok[i, j])
            except ValueError:
                raise InputError(
                    f"expected a number in column {names[j]!r}, got {tokens[i, j]!r}",
                    path, numbers[i],
                ) from None
        raise  # pragma: no cover - astype failed but every token parses
    check = np.broadcast_to(np.asarray(finite, dtype=bool), (tok.shape[0],))
    bad = ~np.isfinite(out) & check[:, None]
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(
            f"expected a finite number in column {names[j]!r}, got {tokens[i, j]!r}",
            path, numbers[i],
        )
    return out


def to_int(
    tokens: np.ndarray, numbers: Sequence[int], path: str | PathLike, names: Sequence[str]
) -> np.ndarray:
    """Convert a (N, K) token array to int64, naming the line and column of a bad token."""
    tok = np.asarray(tokens, dtype=object)
    out = np.empty(tok.shape, dtype=np.int64)
    for j in range(tok.shape[1]):
        try:
            out[:, j] = [int(s) for s in tok[:, j]]
        except ValueError:
            for i, s in enumerate(tok[:, j]):
                try:
                    int(s)
                except ValueError:
                    raise InputError(
                        f"expected an integer in column {names[j]!r}, got {s!r}", path, numbers[i]
                    ) from None
    return out


def csv_table(path: str | PathLike, required: Sequence[str] = ()) -> tuple[
    list[str], list[int], list[str]
]:
    """Header (stripped names), 1-based line numbers and data lines of a comma-separated table of a
    run directory (UTF-8; every line after the header is data). A missing file, header or
    ``required`` column raises :class:`~rtsgt.errors.InputError`."""
    p = Path(path)
    if not p.is_file():
        raise InputError("file not found (is this an rtsgt run directory?)", p)
    lines = read_text(p, ("utf-8",)).splitlines()
    if not lines:
        raise InputError("empty file, expected a header line", p)
    header = [h.strip() for h in lines[0].split(",")]
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)}; header is {','.join(header)}", p, 1
        )
    return header, list(range(2, len(lines) + 1)), lines[1:]


def read_table(
    path: str | PathLike, required: Sequence[str] = ()
) -> tuple[list[str], np.ndarray]:
    """Header and data (N, len(header)) of a numeric table of a run directory (:func:`csv_table`);
    NaN and infinities are numbers here. A wrong field count or a non-number raises
    :class:`~rtsgt.errors.InputError` naming the line."""
    header, numbers, lines = csv_table(path, required)
    tokens = split_rows(lines, numbers, path, header, ",")
    try:
        data = to_float(tokens, numbers, path, header, finite=False)
    except InputError as exc:  # a run table's message has always begun "not a number"
        raise InputError(f"not a number: {exc.bare_message}", path, exc.line) from None
    return header, data


def first_bad(mask: np.ndarray) -> int | None:
    """Index of the first true element of ``mask``, or None."""
    idx = np.flatnonzero(mask)
    return None if idx.size == 0 else int(idx[0])


def check_distance(
    d: np.ndarray, numbers: Sequence[int], path: str | PathLike, *, where: np.ndarray | None = None
) -> None:
    """Slope distances must be positive (m); ``where`` restricts the check to some rows."""
    bad = ~(d > 0)
    if where is not None:
        bad &= where
    i = first_bad(bad)
    if i is not None:
        raise InputError(
            f"expected a positive slope distance, got {float(d[i])!r} m", path, numbers[i]
        )


def check_zenith(
    v: np.ndarray, numbers: Sequence[int], path: str | PathLike, *, where: np.ndarray | None = None
) -> None:
    """Zenith angles must lie in the open interval (0, pi) rad."""
    bad = ~((v > 0) & (v < np.pi))
    if where is not None:
        bad &= where
    i = first_bad(bad)
    if i is not None:
        raise InputError(
            f"expected a zenith angle in (0, pi) rad, got {float(v[i])!r} rad "
            "(is the column a zenith angle in radians? elevation angles and degrees are not)",
            path, numbers[i],
        )


#: Largest magnitude of a time in seconds, s (module docstring): 1e11 s is the year 5138.
MAX_SECONDS = 1e11

#: Units a too-large time may be in, with their factor to seconds (module docstring).
_SUBSECOND_UNITS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))


def check_seconds(
    t: np.ndarray, numbers: Sequence[int], path: str | PathLike, column: str = "t"
) -> None:
    """Times must be seconds: refuse one that looks like ms, us or ns since the epoch.

    Raises
    ------
    InputError
        Naming the file and the line of the first time with ``|t| >= MAX_SECONDS`` (NaN is
        left to the other checks), the unit it looks like and the date it would then be.
    """
    t = np.asarray(t, dtype=float)
    with np.errstate(invalid="ignore"):
        i = first_bad(np.abs(t) >= MAX_SECONDS)
    if i is None:
        return
    value = float(t[i])
    hint = "is the column in seconds?"
    for unit, factor in _SUBSECOND_UNITS:
        if 1e8 <= abs(value) / factor < MAX_SECONDS:
            date = datetime.fromtimestamp(value / factor, timezone.utc)
            hint = (f"it looks like {unit} since the Unix epoch "
                    f"({date.strftime('%Y-%m-%d %H:%M:%S')} UTC), not seconds: divide the "
                    f"column by {factor:.0e} (the format expects seconds)")
            break
    raise InputError(
        f"time {value!r} in column {column!r} is too large for seconds (|t| >= "
        f"{MAX_SECONDS:.0e} s, the year 5138): {hint}",
        path, numbers[i],
    )


def check_increasing(
    t: np.ndarray, numbers: Sequence[int], path: str | PathLike, column: str = "t"
) -> None:
    """Timestamps must be seconds (:func:`check_seconds`) and strictly increasing; say how to
    fix a duplicate or a step back."""
    check_seconds(t, numbers, path, column)
    dt = np.diff(t)
    i = first_bad(dt <= 0)
    if i is None:
        return
    if dt[i] == 0:
        raise InputError(
            f"duplicated timestamp t = {float(t[i + 1])!r} s (same as line {numbers[i]}): "
            f"remove the duplicate line {numbers[i + 1]}",
            path, numbers[i + 1],
        )
    raise InputError(
        f"timestamp t = {float(t[i + 1])!r} s is earlier than t = {float(t[i])!r} s "
        f"on line {numbers[i]}: "
        "timestamps must increase; sort the file by time (e.g. `sort -g -k1`) "
        f"or remove the out-of-order line {numbers[i + 1]}",
        path, numbers[i + 1],
    )


def check_header(
    found: Sequence[str], expected: Sequence[str], path: str | PathLike, number: int
) -> None:
    """The header line must name exactly ``expected`` (case-insensitive, spaces ignored)."""
    got = [c.strip().lower() for c in found]
    if got != [c.lower() for c in expected]:
        raise InputError(
            f"expected the header {' , '.join(expected)!r}, got {' , '.join(found)!r}",
            path, number,
        )


def find_columns(
    header: Sequence[str],
    required: Iterable[str],
    path: str | PathLike,
    number: int,
    optional: Iterable[str] = (),
) -> dict[str, int]:
    """Positions of named columns in a header (exact names, case-insensitive)."""
    names = [h.strip().lower() for h in header]
    pos: dict[str, int] = {}
    for name in list(required) + list(optional):
        if name.lower() in names:
            pos[name] = names.index(name.lower())
    missing = [name for name in required if name not in pos]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)} in the header; got {', '.join(header)}",
            path, number,
        )
    return pos


def fmt_float(x: float) -> str:
    """Shortest text that reads back as exactly the same float64."""
    return repr(float(x))


#: Values of a table formatted and written at a time (:func:`table_chunks`): a few MB of text.
TABLE_CHUNK_VALUES = 1 << 17


def table_chunks(
    data: np.ndarray,
    *,
    header: str | None = None,
    sep: str = ",",
    fmt: str | Sequence[str] | None = None,
    rows: int | None = None,
) -> Iterator[str]:
    """Yield the text of a table ``data`` (N, K), ``rows`` lines at a time (default about
    :data:`TABLE_CHUNK_VALUES` values), after an optional ``header`` line: values joined by
    ``sep``, formatted by ``fmt`` (one or per column; None: :func:`fmt_float`, the shortest exact
    text), so that a large table is never whole in memory as text."""
    a = np.asarray(data, dtype=float)
    if rows is None:
        rows = max(1, TABLE_CHUNK_VALUES // max(a.shape[1] if a.ndim == 2 else 1, 1))
    if header is not None:
        yield header + "\n"
    if fmt is not None:
        line = sep.join([fmt] * a.shape[1] if isinstance(fmt, str) else fmt) + "\n"
    for start in range(0, a.shape[0], rows):
        block = a[start:start + rows].tolist()
        if fmt is None:
            yield "".join(sep.join(map(fmt_float, r)) + "\n" for r in block)
        else:
            yield "".join(line % tuple(r) for r in block)


def table_text(
    data: np.ndarray,
    *,
    header: str | None = None,
    sep: str = ",",
    fmt: str | Sequence[str] | None = None,
) -> str:
    """The whole text of :func:`table_chunks` (same arguments), lines ending in ``"\n"``."""
    return "".join(table_chunks(data, header=header, sep=sep, fmt=fmt))


def atomic_write_text(path: str | PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file and :func:`os.replace`.

    The file appears complete or not at all: an error while writing leaves any previous file
    untouched and removes the temporary file.
    """
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | PathLike, data: bytes | Iterable[bytes],
                       before_replace=None) -> None:
    """Write ``data`` (bytes, or consecutive pieces of them) to ``path`` through a temporary
    file beside it and :func:`os.replace` (permissions of the user's umask), as
    :func:`atomic_write_text`.

    ``before_replace``: called with no argument just before the temporary file replaces
    ``path`` (a last check that the target may still be written); what it raises leaves
    ``path`` untouched.
    """
    p = Path(path)
    directory = p.parent if str(p.parent) else Path(".")
    if not directory.is_dir():
        raise InputError("cannot write: the directory does not exist", p)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            for piece in (data,) if isinstance(data, bytes | bytearray) else data:
                f.write(piece)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        if before_replace is not None:
            before_replace()
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
