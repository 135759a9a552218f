"""The suite's CI policy (tests/conftest.py), run on a throwaway test file in a child pytest."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent


def _pytest(tmp_path: Path, body: str, ci: bool) -> subprocess.CompletedProcess:
    (tmp_path / "test_probe.py").write_text(body)
    env = {**os.environ, "CI": "true" if ci else "", "PYTHONPATH": str(TESTS)}
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-rs",
            "-p",
            "conftest",
            "-p",
            "no:cacheprovider",
            "--rootdir",
            str(tmp_path),
            str(tmp_path / "test_probe.py"),
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
    )


PROBE = """import pytest


def test_needs_an_extra():
    pytest.skip("the extra is missing")


@pytest.mark.gpu
def test_on_gpu():
    assert False
"""


@pytest.mark.parametrize("ci, rc", [(True, 1), (False, 0)])
def test_a_skip_fails_the_run_only_under_ci_and_gpu_tests_need_cuda(tmp_path, ci, rc):
    import torch

    done = _pytest(tmp_path, PROBE, ci)
    if torch.cuda.is_available():  # the GPU test runs (and fails) where CUDA exists
        rc = 1
    else:
        assert "1 deselected" in done.stdout, done.stdout
    assert done.returncode == rc, done.stdout + done.stderr
    assert ("CI=true: 1 skipped test(s) fail the run" in done.stdout) is ci
