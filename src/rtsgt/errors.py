"""Exception hierarchy of rtsgt.

Every error rtsgt raises on purpose derives from :class:`RtsgtError`; the CLI turns it into a
one-line message and exit code 1. Errors about user input subclass :class:`ValueError` as well,
so that library users can catch them either way.
"""

from __future__ import annotations

from os import PathLike


class RtsgtError(Exception):
    """Root of all rtsgt errors."""


class InputError(RtsgtError, ValueError):
    """Bad input data: a file, a line or a value that cannot be used.

    Parameters
    ----------
    message : str
        What is wrong and, where possible, what to do about it.
    path : str or PathLike, optional
        The file the problem is in.
    line : int, optional
        1-based line number in ``path``.
    """

    def __init__(self, message: str, path: str | PathLike | None = None, line: int | None = None):
        self.path = None if path is None else str(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = self.path if line is None else f"{self.path}:{line}"
            where += ": "
        super().__init__(where + message)
        self.bare_message = message


class ConfigError(InputError):
    """Invalid deployment configuration (TOML)."""


class GeometryError(RtsgtError, ValueError):
    """Degenerate geometry: collinear points, too few points, a reflection, ..."""


class ExcitationError(InputError):
    """A parameter asked for that the data do not determine: the trajectory does not excite it
    (a lever arm from a straight drive). The message says which, by how much, and what to do."""


class ExtrapolationError(InputError):
    """A query outside the support of a track (beyond its ends or across a long gap).

    A bad query is bad input: this is an :class:`InputError` (and so a ``ValueError``)."""


class ConvergenceError(RtsgtError, RuntimeError):
    """An iterative solver did not converge within ``max_iter``."""


class RtsgtWarning(UserWarning):
    """Something the user should know about a result that is still produced (a weather record
    that does not cover the measurements, a surveyed distance the tracking disagrees with, ...).

    The CLI prints each as one ``warning: ...`` line on stderr; a run also records them in
    ``summary.json`` under ``warnings``."""
