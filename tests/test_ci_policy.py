"""The suite's CI policy (tests/conftest.py), run by pytest on a throwaway test file."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

PROBE = """import pytest


def test_needs_an_extra():
    pytest.skip("the extra is missing")


@pytest.mark.gpu
def test_on_gpu():
    assert False
"""


@pytest.mark.parametrize("ci, rc", [(True, 1), (False, 0)])
def test_a_skip_fails_the_run_only_under_ci_and_gpu_tests_need_cuda(
    pytester, monkeypatch, request, ci, rc
):
    """A pytest session of its own, with this suite's conftest as its plugin (in this process:
    a child pytest would spend 3 s importing torch again). The module is taken from this
    session by its path: the name ``conftest`` is every conftest.py's."""
    conftest = request.config.pluginmanager.get_plugin(str(Path(__file__).with_name("conftest.py")))
    assert conftest is not None and hasattr(conftest, "pytest_sessionfinish")
    monkeypatch.setenv("CI", "true" if ci else "")
    probe = pytester.makepyfile(test_probe=PROBE)
    done = pytester.runpytest_inprocess(
        "-q", "-rs", "-p", "no:cacheprovider", probe, plugins=[conftest]
    )
    out = done.stdout.str()
    if torch.cuda.is_available():  # the GPU test runs (and fails) where CUDA exists
        rc = 1
    else:
        assert "1 deselected" in out, out
    assert done.ret == rc, out + done.stderr.str()
    assert ("CI=true: 1 skipped test(s) fail the run" in out) is ci
