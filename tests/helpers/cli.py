"""The ``beadsight`` command line run in the test's own process.

A child ``python -m beadsight`` pays 2-3 s to import torch, and a training one another ~3 s
for ``torch._dynamo`` (AdamW imports it); in-process, a pytest worker pays that once. Tests
keep a child process only where the process boundary is what they test: signals, SIGKILL,
OS exit codes, resource limits, the wall clock of a whole run.
"""

from __future__ import annotations

import io
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass

import torch

from beadsight.cli import main


@dataclass(frozen=True)
class Ran:
    """What ``beadsight ARGS`` did: its exit code and what it printed."""

    returncode: int
    stdout: str
    stderr: str


def run_beadsight(*args) -> Ran:
    """``beadsight ARGS`` through :func:`beadsight.cli.main`, its output captured.

    torch's thread count is put back afterwards: ``--threads`` sets it for the process, and
    the worker's later tests must not inherit it."""
    threads = torch.get_num_threads()
    out, err = io.StringIO(), io.StringIO()
    try:
        with redirect_stdout(out), redirect_stderr(err):
            code = main([str(a) for a in args])
    finally:
        torch.set_num_threads(threads)
    return Ran(code, out.getvalue(), err.getvalue())


def beadsight_ok(*args) -> str:
    """``beadsight ARGS`` in-process; fails the test, with what it printed, unless it exits 0.
    Returns its stdout."""
    ran = run_beadsight(*args)
    assert ran.returncode == 0, f"beadsight {args[0]} failed:\n{ran.stdout}\n{ran.stderr[-3000:]}"
    return ran.stdout
