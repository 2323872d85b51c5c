"""Shared test settings.

Rich wraps the CLI's output at the console's width (80 columns when stdout is not a
terminal), so a phrase can break across lines at a place that depends on the length of a
temporary path (pytest-xdist's ``popen-gw<N>`` folders make it depend on the number of
workers). Every test sees a console wide enough never to wrap; a test that needs another
width passes its own ``COLUMNS``.
"""
import pytest


@pytest.fixture(autouse=True)
def _wide_console(monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")
