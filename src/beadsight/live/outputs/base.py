"""The base of the network outputs: a live listener that publishes from its own thread, so
that sensing never waits for it, with one rule for slow consumers.

**The slow-client rule.** No reading older than ``max_age_s`` (0.5 s) is handed on, and
every reading that is not handed on is counted in ``skipped``. The sensing thread calls
:meth:`OutputListener.push` for every reading; it only stores the update with the time it
arrived (keeping the newest :attr:`queue_size`; an older one is skipped) and returns. A
worker thread hands updates to :meth:`publish`, which subclasses implement (ROS 2 over
DDS, the Foxglove WebSocket server), skipping any that waited longer than ``max_age_s``;
what a subclass does after ``publish`` (its own per-client queue) is bounded by the
subclass (see ``docs/live.md``, *Slow clients*). The worker also hands the sensor's state
and health to :meth:`publish_health`: at once when the sensor's state or the health
state changes, else every :data:`HEALTH_PERIOD_S` while readings flow. A state change
is published in order with the readings around it (state changes are never dropped), so
"ended" comes after the last reading.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from typing import Any

from beadsight.live.config import HEALTH_PERIOD_S, MAX_AGE_S, check_positive
from beadsight.live.ros.messages import health_report

logger = logging.getLogger(__name__)

DEFAULT_QUEUE_SIZE = 4  # updates waiting for the worker before the oldest is dropped
FINISH_TIMEOUT_S = 5.0  # finish() waits this long for the worker to drain
UPDATE, STATUS = "update", "status"


class OutputListener:
    """Base of every network output (a ``beadsight.live.listeners.LiveListener``).

    Subclasses implement :meth:`publish` (one ``LiveUpdate``), optionally
    :meth:`publish_health` (a :func:`~beadsight.live.ros.messages.health_report`) and
    :meth:`close` (release resources, called on the worker thread after the last
    publish). ``published`` and ``skipped`` count updates (skipped: the queue was full,
    or the update waited longer than ``max_age_s``); ``errors`` counts publish calls
    that raised (each is logged); ``busy_s`` is the time spent in them. An update's
    health is its ``health`` attribute (``.state``, ``.figures``), where the sensor
    tracks it.
    """

    name = "output"

    def __init__(self, *, max_age_s: float = MAX_AGE_S, queue_size: int = DEFAULT_QUEUE_SIZE):
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f"{self.name}: queue_size must be an integer >= 1, got {queue_size}")
        self.max_age_s = check_positive(max_age_s, f"{self.name}: max_age_s", "s")
        self.queue_size = queue_size
        # ("update", (monotonic arrival s, update)) | ("status", status), in order
        self._events: deque[tuple[str, Any]] = deque()
        self._queued = 0  # updates in _events
        self._cond = threading.Condition()
        self._finished = False
        self._status: Any = None  # the newest LiveStatus (worker thread only)
        self._latest_health: Any = None  # the newest update's health (None: not tracked)
        self._health_state: Any = None  # health state last published
        self._health_due = -math.inf  # time.monotonic() of the next periodic health
        self.published = 0
        self.skipped = 0
        self.errors = 0
        self.busy_s = 0.0  # time spent in publish(), s
        self.arrived_s = 0.0  # time.monotonic() when the update being published was pushed
        self._thread = threading.Thread(
            target=self._work, name=f"beadsight-{self.name}", daemon=True
        )
        self._thread.start()

    # --- called on the sensing thread: store and return ---------------------------------
    def push(self, update: Any) -> None:
        with self._cond:
            if self._queued == self.queue_size:  # skip the oldest update (never a status)
                oldest = next(i for i, (kind, _) in enumerate(self._events) if kind == UPDATE)
                del self._events[oldest]
                self._queued -= 1
                self.skipped += 1
            self._events.append((UPDATE, (time.monotonic(), update)))
            self._queued += 1
            self._cond.notify()

    def status(self, status: Any) -> None:
        """A change of the sensor's state: published in order with the updates around it."""
        with self._cond:
            self._events.append((STATUS, status))
            self._cond.notify()

    def finish(self) -> None:
        """Publish what is waiting, then stop the worker and :meth:`close` (idempotent)."""
        with self._cond:
            self._finished = True
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(FINISH_TIMEOUT_S)

    # --- for subclasses ---------------------------------------------------------------
    def publish(self, update: Any) -> None:
        raise NotImplementedError

    def publish_health(self, report: dict[str, Any]) -> None:
        """Publish the sensor's state and health (default: nothing)."""

    def close(self) -> None:
        """Release what the publisher holds (default: nothing)."""

    # --- the worker ---------------------------------------------------------------------
    def _next(self) -> tuple[str | None, Any]:
        """The next event; (None, None) once finished and all is published. Updates that
        waited longer than ``max_age_s`` are skipped here."""
        with self._cond:
            while True:
                while not (self._events or self._finished):
                    self._cond.wait()
                if not self._events:
                    return None, None
                kind, item = self._events.popleft()
                if kind != UPDATE:
                    return kind, item
                self._queued -= 1
                arrived_s, update = item
                if time.monotonic() - arrived_s <= self.max_age_s:
                    self.arrived_s = arrived_s
                    return kind, update
                self.skipped += 1

    def _guarded(self, method: Any, arg: Any) -> bool:
        try:
            method(arg)
            return True
        except Exception:
            self.errors += 1
            logger.exception("%s: publishing failed", self.name)
            return False

    def _report_health(self, changed: bool, update: Any | None) -> None:
        """Publish the health report if the sensor's state (``changed``) or the health
        state changed, or, while readings flow, every :data:`HEALTH_PERIOD_S`."""
        if update is not None:
            self._latest_health = getattr(update, "health", None)
            changed = changed or getattr(self._latest_health, "state", None) != self._health_state
        now = time.monotonic()
        if not changed and (update is None or now < self._health_due):
            return
        self._health_state = getattr(self._latest_health, "state", None)
        self._health_due = now + HEALTH_PERIOD_S
        report = health_report(self._status, self._latest_health, time.time())
        self._guarded(self.publish_health, report)

    def _work(self) -> None:
        try:
            while True:
                kind, item = self._next()
                if kind is None:
                    return
                if kind == STATUS:
                    self._status = item
                    self._report_health(True, None)
                    continue
                start = time.perf_counter()
                self.published += self._guarded(self.publish, item)
                self.busy_s += time.perf_counter() - start
                self._report_health(False, item)
        finally:
            try:
                self.close()
            except Exception:
                logger.exception("%s: close failed", self.name)
