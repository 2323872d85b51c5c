"""The ``rtsgt`` console script: the command line, with Ctrl-C handled from its first moment.

It imports the application (:mod:`rtsgt.cli.main`) inside the ``try`` that turns an interrupt
into :data:`INTERRUPTED_LINE` and :data:`EXIT_INTERRUPTED`, at start-up included; after it,
nothing more on stderr (docs/cli.md#errors-warnings-and-exit-statuses).
"""

from __future__ import annotations

import atexit
import os
import signal
import sys

from rtsgt.allocator import limit_arenas
from rtsgt.choices import EXIT_INTERRUPTED, INTERRUPTED_LINE, WRITE_PROCESSES_ENV

#: The BLAS thread counts the command line runs with unless the environment sets them: one
#: (many small matrices; docs/benchmarks.md#speed).
BLAS_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


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
    """After the interrupt's line: no further interrupt, nothing more on stderr at exit."""
    _ignore_interrupts()
    atexit.register(_silence_stderr)


def interrupted() -> int:
    """Print :data:`INTERRUPTED_LINE`, then nothing more; returns :data:`EXIT_INTERRUPTED`."""
    _ignore_interrupts()
    try:
        sys.stderr.write(INTERRUPTED_LINE + "\n")
    except (OSError, ValueError):  # stderr closed: nothing to say it on
        pass
    _nothing_more()
    return EXIT_INTERRUPTED


def main() -> None:
    """Run the command line of ``sys.argv``; exits with the command's status."""
    status: int | str | None
    limit_arenas()  # (rtsgt.allocator: docs/benchmarks.md#speed)
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
