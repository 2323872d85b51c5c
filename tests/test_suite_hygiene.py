"""The test suite leaves the machine alone: it installs nothing, and says why it skips.

The browser test of the HTML report needs Chromium. Where there is none, it must skip with its
reason, and never try to install one (it used to run ``apt-get install chromium`` as root).
The test runs it in a separate pytest whose PATH has no browser and where ``apt-get``, ``apt``,
``dpkg``, ``sudo`` and ``pip`` are stand-ins that record any call; none may be called.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
INSTALLERS = ("apt-get", "apt", "dpkg", "sudo", "pip", "pip3", "snap")


def test_browser_test_skips_without_chromium_and_installs_nothing(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log = tmp_path / "calls.log"
    for tool in INSTALLERS:
        script = bin_dir / tool
        script.write_text(f'#!/bin/sh\necho "{tool} $*" >> "{log}"\nexit 1\n')
        script.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("PATH", "PYTEST_ADDOPTS")}
    env["PATH"] = str(bin_dir)  # no chromium, and only the recording stand-ins
    p = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
         "tests/test_report.py::test_report_in_headless_chromium"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "1 skipped" in p.stdout, p.stdout
    assert "no Chromium on PATH" in p.stdout, p.stdout
    assert not log.exists(), log.read_text()
