"""Fixtures of the live tests: one tiny model per test module, the thread-leak check
(``pytestmark = pytest.mark.usefixtures("no_thread_leaks")`` in the modules that use it),
and ``dds``: DDS on the loopback interface in a fresh ROS domain per test."""

from __future__ import annotations

import itertools
import random
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


LOOPBACK_CONFIG = """<?xml version="1.0" encoding="UTF-8"?>
<CycloneDDS xmlns="https://cdds.io/config">
  <Domain Id="any">
    <General>
      <Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
      <AllowMulticast>false</AllowMulticast>
    </General>
    <Discovery>
      <ParticipantIndex>auto</ParticipantIndex>
      <Peers><Peer address="127.0.0.1"/></Peers>
    </Discovery>
    <Tracing>
      <Verbosity>config</Verbosity>
      <OutputFile>TRACE_DIR/dds-${CYCLONEDDS_PID}.log</OutputFile>
    </Tracing>
  </Domain>
</CycloneDDS>
"""
_DOMAINS = itertools.count(random.randrange(1, 200))  # a fresh domain per test


@pytest.fixture
def dds(tmp_path, monkeypatch):
    """(domain id, trace folder): loopback-only Cyclone for this process and its children.
    After the test, every participant's trace must show it selected 127.0.0.1 alone."""
    traces = tmp_path / "dds"
    traces.mkdir()
    config = tmp_path / "cyclonedds.xml"
    config.write_text(LOOPBACK_CONFIG.replace("TRACE_DIR", str(traces)))
    monkeypatch.setenv("CYCLONEDDS_URI", config.as_uri())
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    yield next(_DOMAINS) % 200 + 1, traces
    logs = list(traces.glob("dds-*.log"))
    assert logs, "no Cyclone trace: the loopback config was not used"
    for log in logs:
        text = log.read_text()
        assert "selected interfaces: lo " in text, f"{log.name} did not select loopback alone"
        assert "AllowMulticast/#text: false" in text
