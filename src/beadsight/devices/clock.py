"""Device time: host time, or simulated time shared by the virtual devices of one rig.

Simulated seconds run ``time_scale`` times faster than the host's monotonic clock
(1.0 = real time, the default; tests use e.g. 10 to press in a tenth of the time). Every
duration a virtual device models (move time, dwell, sample period, frame period, boot
delay) is in simulated seconds; the drivers on the other side only ever see host time.
A ``SimClock()`` at the default scale is the host clock: the cameras pace frames on it.
Capture timestamps are host time (:meth:`SimClock.stamp`), except on a
:class:`SteppedClock`, whose time moves only when a device waits: timing logic (frame
gaps, delivered rates) tested on it sees no host jitter; and on a :class:`FrameClock`,
which stamps the frames of a camera played as fast as it is read one period apart.
"""

from __future__ import annotations

import threading
import time

from beadsight.devices.base import host_now

STEPPED_EPOCH_UNIX = 1_700_000_000.0  # a SteppedClock's time 0 as a unix time, s


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

    def stamp(self) -> tuple[float, float]:
        """``(t_unix, t_mono)`` of a capture now: the host's clocks."""
        return host_now()


class SteppedClock(SimClock):
    """Simulated time that moves only when a device waits for it: each
    :meth:`wait_until` jumps to its target after ``step_real_s`` host seconds (so a
    device on it runs fast without spinning), and capture stamps are this time, not the
    host's. For tests of timing logic that a loaded machine's jitter would upset."""

    def __init__(self, step_real_s: float = 0.001):
        super().__init__(1.0)
        self.step_real_s = float(step_real_s)
        self._t = 0.0
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def to_real_s(self, sim_s: float) -> float:
        return 0.0

    def wait_until(self, sim_t: float, stop: threading.Event) -> bool:
        if stop.wait(self.step_real_s):
            return False
        with self._lock:
            self._t = max(self._t, float(sim_t))
        return True

    def stamp(self) -> tuple[float, float]:
        t = self.now()
        return STEPPED_EPOCH_UNIX + t, t


class FrameClock(SimClock):
    """Capture stamps exactly one frame period apart, whatever the host does, for a camera
    played as fast as it is read (``realtime=False``): the logic downstream that is timed
    by capture stamps (rest references once per second, health, gap detection) then sees
    the camera's own time, and a run repeats on any machine at any speed."""

    def __init__(self, fps: float):
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        super().__init__(1.0)
        self.period_s = 1.0 / float(fps)
        self._frames = 0
        self._lock = threading.Lock()

    def stamp(self) -> tuple[float, float]:
        with self._lock:
            t = self._frames * self.period_s
            self._frames += 1
        return STEPPED_EPOCH_UNIX + t, t
