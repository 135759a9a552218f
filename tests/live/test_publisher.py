"""The background publisher: sensing never waits for it, it drops the oldest readings
when it falls behind (never a state change), and publishes state changes in order."""

from __future__ import annotations

import threading

import pytest
from helpers.live import wait_until
from helpers.publish import Health

from beadsight.live.listeners import LiveStatus
from beadsight.live.outputs.base import OutputListener

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads


class Recorder(OutputListener):
    """Publishes into a list, each publish waiting until ``gate`` opens."""

    name = "recorder"

    def __init__(self, queue_size: int):
        self.gate = threading.Event()
        self.events: list = []
        self.closed = False
        super().__init__(queue_size=queue_size)

    def publish(self, update) -> None:
        self.gate.wait(10)
        if update.i < 0:
            raise ValueError("cannot publish")
        self.events.append(update)

    def publish_health(self, report) -> None:
        self.events.append((report["sensor_state"], report["state"]))

    def close(self) -> None:
        self.closed = True


class Update:
    def __init__(self, i: int, health=None):
        self.i, self.health = i, health

    def __eq__(self, other) -> bool:
        return isinstance(other, Update) and other.i == self.i

    def __hash__(self) -> int:
        return self.i


def test_slow_publisher_drops_oldest_readings_keeps_state_changes_in_order():
    pub = Recorder(queue_size=3)
    pub.status(LiveStatus("ok", "sim", 0.0))
    wait_until(lambda: pub.events == [("ok", None)], 5, "the first state")
    pub.push(Update(0))  # taken by the worker, which waits at the gate
    wait_until(lambda: pub._queued == 0, 5, "the worker to take update 0")
    for i in range(1, 8):  # the sensing thread never waits
        pub.push(Update(i))
    pub.status(LiveStatus("ended", "end of video", 1.0))
    pub.push(Update(8))
    assert pub.skipped == 5 and pub._queued == 3  # 1..5 skipped; 6, 7 and 8 wait
    pub.gate.set()
    pub.finish()
    assert pub.events == [
        ("ok", None),
        Update(0),
        Update(6),
        Update(7),
        ("ended", None),  # after the readings before it, before the one after
        Update(8),
    ]
    assert (pub.published, pub.errors, pub.closed) == (4, 0, True)


def test_health_changes_publish_at_once_and_errors_are_counted():
    pub = Recorder(queue_size=16)
    pub.gate.set()
    pub.status(LiveStatus("ok", "sim", 0.0))
    for i, state in enumerate(["ok", "ok", "drifting", "drifting", "recalibrate"]):
        pub.push(Update(i, Health(state, {"shift_px": i})))
    pub.push(Update(-1, Health("recalibrate", {})))  # its publish fails
    pub.finish()
    health = [e for e in pub.events if isinstance(e, tuple)]
    assert health == [("ok", None), ("ok", "ok"), ("ok", "drifting"), ("ok", "recalibrate")]
    assert (pub.published, pub.errors) == (5, 1)
