"""The suite's CI policy (tests/conftest.py), run by pytest on a throwaway test file."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from xdist.scheduler import WorkStealingScheduling

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


class _Item:
    """What :func:`slow_first` reads of a pytest item."""

    def __init__(self, nodeid: str, slow: bool):
        self.nodeid, self.slow = nodeid, slow

    def get_closest_marker(self, name: str):
        return name == "slow" and self.slow or None


class _Worker:
    """What xdist's scheduler reads of a worker: it records the tests sent to it."""

    shutting_down = False

    def __init__(self, name: str):
        self.gateway = SimpleNamespace(id=name)
        self.sent: list[int] = []

    def send_runtest_some(self, indices):
        self.sent += indices


@pytest.mark.parametrize("workers, tests, every", [(3, 100, 9), (2, 57, 5), (4, 30, 2)])
def test_xdist_starts_each_worker_on_its_slow_tests(pytester, request, workers, tests, every):
    """xdist's own worksteal scheduler, given the suite's order, sends each worker its share
    of the slow tests first; every test is sent once, the others keep their order."""
    conftest = request.config.pluginmanager.get_plugin(str(Path(__file__).with_name("conftest.py")))
    items = [_Item(f"t{i}", slow=i % every == every - 1) for i in range(tests)]
    ordered = conftest.slow_first(items, workers)
    scheduler = WorkStealingScheduling(pytester.parseconfig("--tx", f"{workers}*popen"))
    nodes = [_Worker(f"gw{k}") for k in range(workers)]
    for node in nodes:
        scheduler.add_node(node)
    for node in nodes:
        scheduler.add_node_collection(node, [item.nodeid for item in ordered])
    scheduler.schedule()
    sent = [[ordered[i] for i in node.sent] for node in nodes]
    assert sorted(item.nodeid for share in sent for item in share) == sorted(
        i.nodeid for i in items
    )
    slow = [item for item in items if item.slow]
    for share in sent:
        flags = [item.slow for item in share]
        assert flags == sorted(flags, reverse=True)  # the slow ones first
        assert abs(sum(flags) - len(slow) / workers) < 1
    assert [i for i in ordered if not i.slow] == [i for i in items if not i.slow]
