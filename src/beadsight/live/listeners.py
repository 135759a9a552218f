"""What the live sensing thread produces, and the listeners that receive it.

:class:`LiveUpdate` (a reading with its frame) and :class:`LiveStatus` (the sensor's
state) go to every :class:`LiveListener` registered with
:meth:`beadsight.live.sensor.LiveSensor.add_listener`. Listeners are called on the
sensing thread and must return quickly: :class:`UpdateQueue` hands updates to a
consumer on another thread.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from beadsight.inference.predictor import PressureReading

logger = logging.getLogger(__name__)

READING_QUEUE_SIZE = 256  # readings() buffers this many before dropping the oldest
STATES = ("starting", "ok", "warming_up", "no_signal", "ended", "stopped", "error")


@dataclass(frozen=True)
class LiveUpdate:
    """One reading with the frame it came from (what the viewer and recorders get).

    reading: the predictor's :class:`~beadsight.inference.predictor.PressureReading` (its
        ``latency_s`` is the inference time only).
    frame_rgb: (S, S, 3) uint8 RGB model input (the newest frame of the window).
    latency_s: capture -> reading available, s (capture timestamp to the moment the
        reading left the predictor).
    reference_force_n: the true force if the source knows it (the simulator), else NaN.
    source_index: the frame's index in the source: its row in a replayed dataset, else its
        capture index (:attr:`beadsight.devices.Frame.source_index`).
    health: the sensor's drift health (:class:`~beadsight.health.monitor.HealthReport`:
        ``state``, ``message``, ``figures``), or None where it is not tracked.
    """

    reading: PressureReading
    frame_rgb: np.ndarray
    latency_s: float
    reference_force_n: float
    source_index: int
    health: Any = None


@dataclass(frozen=True)
class LiveStatus:
    """The sensor's state: one of :data:`STATES`, a human-readable message, and since when."""

    state: str
    message: str
    since_s: float  # time.time() of the change

    @property
    def has_signal(self) -> bool:
        return self.state in ("ok", "warming_up")


class LiveListener(Protocol):
    """Receives everything the sensing thread produces; every method must return quickly."""

    def push(self, update: LiveUpdate) -> None: ...

    def status(self, status: LiveStatus) -> None: ...

    def finish(self) -> None: ...


class CallbackListener:
    """Calls ``callback(reading)`` (``unwrap``) or ``callback(update)`` per update."""

    def __init__(self, callback: Callable[[Any], None], unwrap: bool):
        self.callback, self.unwrap = callback, unwrap

    def push(self, update: LiveUpdate) -> None:
        self.callback(update.reading if self.unwrap else update)

    def status(self, status: LiveStatus) -> None:
        pass

    def finish(self) -> None:
        pass


class UpdateQueue:
    """A bounded queue of updates for one consumer; drops the oldest when full.

    ``get(timeout)`` returns the next update, or None on timeout; after :meth:`finish`
    and once empty it raises :class:`StopIteration`-free ``EOFError``.
    """

    def __init__(self, maxsize: int = READING_QUEUE_SIZE):
        self._items: deque[LiveUpdate] = deque(maxlen=maxsize)
        self._cond = threading.Condition()
        self._finished = False
        self.dropped = 0

    def push(self, update: LiveUpdate) -> None:
        with self._cond:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
                if self.dropped == 1 or self.dropped % 100 == 0:
                    logger.warning("a reading consumer is too slow: %d dropped", self.dropped)
            self._items.append(update)
            self._cond.notify()

    def status(self, status: LiveStatus) -> None:
        pass

    def finish(self) -> None:
        with self._cond:
            self._finished = True
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> LiveUpdate | None:
        with self._cond:
            self._cond.wait_for(lambda: self._items or self._finished, timeout)
            if self._items:
                return self._items.popleft()
            if self._finished:
                raise EOFError
            return None
