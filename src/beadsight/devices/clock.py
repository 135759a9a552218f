"""Device time: host time, or simulated time shared by the virtual devices of one rig.

Simulated seconds run ``time_scale`` times faster than the host's monotonic clock
(1.0 = real time, the default; tests use e.g. 10 to press in a tenth of the time). Every
duration a virtual device models (move time, dwell, sample period, frame period, boot
delay) is in simulated seconds; the drivers on the other side only ever see host time.
A ``SimClock()`` at the default scale is the host clock: the cameras pace frames on it.
"""

from __future__ import annotations

import threading
import time


class SimClock:
    """Simulated seconds since creation, ``time_scale`` x faster than ``time.monotonic``."""

    def __init__(self, time_scale: float = 1.0):
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        self.time_scale = float(time_scale)
        self._t0_mono = time.monotonic()

    def now(self) -> float:
        """Simulated seconds since the clock was created."""
        return (time.monotonic() - self._t0_mono) * self.time_scale

    def to_real_s(self, sim_s: float) -> float:
        """Host seconds that ``sim_s`` simulated seconds take."""
        return sim_s / self.time_scale

    def wait_until(self, sim_t: float, stop: threading.Event) -> bool:
        """Sleep until simulated time ``sim_t``; False if ``stop`` was set first."""
        delay = self.to_real_s(sim_t - self.now())
        if delay <= 0:
            return not stop.is_set()
        return not stop.wait(delay)
