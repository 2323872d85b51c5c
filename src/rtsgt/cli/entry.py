"""The ``rtsgt`` console script: the command line, with Ctrl-C handled from its first moment.

The application (:mod:`rtsgt.cli.main`) takes a few seconds to import (numpy, scipy,
matplotlib, ...). This module imports nothing heavy: it imports the application inside the
``try`` that turns an interrupt into one line on stderr, :data:`INTERRUPTED_LINE`, and the exit
status :data:`EXIT_INTERRUPTED`, as an interrupt while a command runs is
(:mod:`rtsgt.cli.main`): never a traceback, at start-up included. After the command (or the
interrupt), a further Ctrl-C while the interpreter shuts down is ignored rather than shown as
a traceback, and after the interrupt's line the process writes nothing more on stderr. ``rtsgt --version`` answers without importing the application.
"""

from __future__ import annotations

import os
import signal
import sys

#: Exit status of an interrupted command (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130
#: The line an interrupted command prints on stderr.
INTERRUPTED_LINE = "error: interrupted"


def _ignore_interrupts() -> None:
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except (ValueError, OSError):  # pragma: no cover - not the main thread
        pass


def _nothing_more() -> None:
    """After the interrupt's line, nothing more on this process's stderr: what library code
    still says while the interpreter shuts down (e.g. Dask closing a cluster whose start was
    interrupted) is noise."""
    _ignore_interrupts()
    try:
        sys.stderr.flush()
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stderr.fileno())
    except (OSError, ValueError):  # stderr closed already
        pass


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


def main() -> None:
    """Run the command line of ``sys.argv``; exits with the command's status."""
    status: int | str | None
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
    _ignore_interrupts()
    sys.exit(status)
