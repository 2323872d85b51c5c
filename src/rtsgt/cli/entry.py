"""The ``rtsgt`` console script: the command line, with Ctrl-C handled from its first moment.

The application (:mod:`rtsgt.cli.main`) imports light modules only (a tenth of a second); a
command imports numpy, scipy, the pipeline, ... when it runs, which takes seconds. This module
imports nothing heavy: it imports the application inside the ``try`` that turns an interrupt
into one line on stderr, :data:`INTERRUPTED_LINE`, and the exit status
:data:`EXIT_INTERRUPTED`, as an interrupt while a command runs is (:mod:`rtsgt.cli.main`):
never a traceback, at start-up included. After the command (or the interrupt), a further Ctrl-C
while the interpreter shuts down is ignored rather than shown as a traceback, and after the
interrupt's line the process writes nothing more on stderr. ``rtsgt --version`` answers without
importing the application.
"""

from __future__ import annotations

import atexit
import ctypes
import os
import signal
import sys

from rtsgt.choices import WRITE_PROCESSES_ENV

#: The BLAS thread counts the command line runs with unless the environment sets them: one.
#: rtsgt's linear algebra is many small matrices (3x3 to a few hundred rows), where a second
#: BLAS thread costs more than it gives (on the 2-core machine: a simulated hour 35.0 -> 26.8 s,
#: the self-checks 7.4 -> 2.5 s; docs/benchmarks.md#speed), and a run then gives the same bits
#: serially as in a Dask worker.
BLAS_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: The most malloc arenas (glibc) the command line runs with: each thread of the numeric
#: stages otherwise keeps an arena of its own, whose freed memory stays with the process (a
#: simulated hour's peak 370 -> 357 MB; one arena: 334 MB; docs/benchmarks.md#speed).
MALLOC_ARENAS = 2
#: glibc's ``mallopt`` parameter ``M_ARENA_MAX``.
_M_ARENA_MAX = -8

#: Exit status of an interrupted command (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130
#: The line an interrupted command prints on stderr.
INTERRUPTED_LINE = "error: interrupted"


def _ignore_interrupts() -> None:
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except (ValueError, OSError):  # pragma: no cover - not the main thread
        pass


def _silence_stderr() -> None:
    """Nothing more on this process's stderr (file descriptor 2)."""
    try:
        sys.stderr.flush()
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stderr.fileno())
    except (OSError, ValueError):  # stderr closed already
        pass


def _nothing_more() -> None:
    """After the interrupt's line: no further interrupt, and, once the interpreter shuts down,
    nothing more on stderr (what library code says then, e.g. Dask closing a cluster whose
    start was interrupted, is noise). A caller of :func:`main` in its own process keeps its
    stderr until it exits."""
    _ignore_interrupts()
    atexit.register(_silence_stderr)


def interrupted() -> int:
    """Print :data:`INTERRUPTED_LINE` on stderr, then nothing more, and ignore further
    interrupts (the command is over); returns :data:`EXIT_INTERRUPTED`."""
    _ignore_interrupts()
    try:
        sys.stderr.write(INTERRUPTED_LINE + "\n")
    except (OSError, ValueError):  # stderr closed: nothing to say it on
        pass
    _nothing_more()
    return EXIT_INTERRUPTED


def _limit_malloc_arenas() -> None:
    """At most :data:`MALLOC_ARENAS` malloc arenas where the C library is glibc (elsewhere,
    nothing): before any thread of the run allocates."""
    try:
        ctypes.CDLL(None).mallopt(_M_ARENA_MAX, MALLOC_ARENAS)
    except (AttributeError, OSError, TypeError):  # not glibc
        pass


def main() -> None:
    """Run the command line of ``sys.argv``; exits with the command's status."""
    status: int | str | None
    _limit_malloc_arenas()
    for name, value in BLAS_THREADS.items():  # before numpy loads; a user's setting wins
        os.environ.setdefault(name, value)
    os.environ.setdefault(WRITE_PROCESSES_ENV, "2")  # rtsgt.io.run_dir.WRITE_PROCESSES
    try:
        if sys.argv[1:] == ["--version"]:  # as the application prints it, without its imports
            from rtsgt import __version__

            sys.stdout.write(f"rtsgt {__version__}\n")
            status = 0
        else:
            from rtsgt.cli.main import app

            app()  # exits (SystemExit) with the status of rtsgt.cli.main
            status = 0
    except SystemExit as exc:
        status = exc.code
        if status == EXIT_INTERRUPTED:  # rtsgt.cli.main printed the line
            _nothing_more()
    except KeyboardInterrupt:
        status = interrupted()
    # Ctrl-C while the interpreter shuts down: ignored (registered last, this runs first of
    # the exit handlers); a caller of main() in its own process keeps its handler till then
    atexit.register(_ignore_interrupts)
    sys.exit(status)
