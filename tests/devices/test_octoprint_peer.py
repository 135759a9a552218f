"""MarlinPrinter against OctoPrint's virtual printer (optional: an independent peer).

OctoPrint pins many packages, so it lives in its own venv: ``scripts/setup.sh --dev`` makes
``.venv-octoprint/``; ``BEADSIGHT_OCTOPRINT_PYTHON`` names another one (docs/hardware.md).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import beadsight

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "octoprint_peer.py"
PYTHON = os.environ.get("BEADSIGHT_OCTOPRINT_PYTHON") or str(ROOT / ".venv-octoprint/bin/python")

pytestmark = pytest.mark.skipif(
    not Path(PYTHON).is_file(),
    reason=f"no OctoPrint python at {PYTHON}: run scripts/setup.sh --dev, or set "
    "BEADSIGHT_OCTOPRINT_PYTHON to a python with OctoPrint installed",
)


def test_press_session_against_octoprint_virtual_printer():
    env = dict(os.environ, PYTHONPATH=str(Path(beadsight.__file__).parents[1]))
    run = subprocess.run(
        [sys.executable, str(SCRIPT), "--octoprint-python", PYTHON],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    summary = re.search(r"^(\d+)/(\d+) steps ok$", run.stdout, re.MULTILINE)
    assert summary is not None, run.stdout + run.stderr
    failed = [
        line
        for line in run.stdout.splitlines()
        if re.match(r"step .*: (FAILED|HUNG|NOT RUN)", line)
    ]
    assert failed == [] and run.returncode == 0, "\n".join(failed) or run.stderr
    assert int(summary.group(2)) >= 25  # the whole session ran
    assert "PrinterDesyncError, finger at Z=10" in run.stdout
