"""Fixtures of the live tests: one tiny model per test module, and the thread-leak check
(``pytestmark = pytest.mark.usefixtures("no_thread_leaks")`` in the modules that use it)."""

from __future__ import annotations

import threading

import pytest
from helpers.live import tiny_model, wait_until


@pytest.fixture
def no_thread_leaks():
    """Every test must stop all the threads it started."""
    before = set(threading.enumerate())
    yield
    wait_until(
        lambda: not [t for t in threading.enumerate() if t not in before and t.is_alive()],
        10,
        "threads of the test to end",
    )


@pytest.fixture(scope="module")
def model():
    """An untrained tiny_model(), shared by the tests of one module."""
    return tiny_model()
