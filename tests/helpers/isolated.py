"""Run test code in a fresh interpreter, so that a crash or a runaway allocation in the code
under test fails one test instead of killing pytest (or the machine)."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import textwrap
from pathlib import Path

import beadsight

SRC = Path(beadsight.__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
MEMORY_LIMIT = 6 << 30  # address space of the child: an absurd allocation fails there, cleanly


def run_isolated(code: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """Run ``code`` (dedented) with beadsight and tests/ importable; fail on a fatal signal."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), str(TESTS)])}

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))

    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=limit,
    )
    assert proc.returncode >= 0, (
        f"the code under test died of signal {-proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    )
    return proc
