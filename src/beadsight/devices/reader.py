"""The background thread behind every reader: cameras, the virtual devices, the rig's recorder.

A :class:`ReaderThread` runs ``target(stop)`` on a named daemon thread; ``target`` loops
until the :class:`threading.Event` ``stop`` is set (waiting on ``stop.wait(...)`` rather
than sleeping, so it ends promptly). :meth:`ReaderThread.stop` sets the event and waits
for the thread, never for itself (a target may stop its own reader), and says so in the
log when the thread outlives the wait.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

logger = logging.getLogger(__name__)

STOP_WAIT_S = 5.0  # default: how long stop() waits for the thread to end


class ReaderThread:
    """One background thread with its own stop event; start it once, stop it any number of times."""

    def __init__(self, name: str, target: Callable[[threading.Event], None]):
        self.name = name
        self.stop_event = threading.Event()
        self._thread = threading.Thread(
            target=target, args=(self.stop_event,), name=name, daemon=True
        )

    def start(self) -> ReaderThread:
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def started(self) -> bool:
        return self._thread.ident is not None

    def stop(self, timeout_s: float = STOP_WAIT_S) -> bool:
        """Set the stop event and wait up to ``timeout_s`` for the thread to end.

        Returns True once it ended (or never started, or this is the thread itself).
        """
        self.stop_event.set()
        if self._thread is threading.current_thread() or self._thread.ident is None:
            return True
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            logger.warning("%s: thread did not stop within %g s", self.name, timeout_s)
            return False
        return True
