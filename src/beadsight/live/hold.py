"""The steady-load hold: a load that stays still keeps its reading.

The network reads pressure from a window of recent frames, and it learned from presses
that come and go: under a load that stays still (an object resting in a gripper) its
force fades to zero within about two seconds (the shipped sim model: 7 N to 0 N in
1.5 s), although the beads are still displaced. A drift filter would do the same. The
hold never lets a still load fade:

* while the frames move, readings pass unchanged;
* when the frames become still (:class:`~beadsight.health.stillness.StillnessDetector`)
  while the sensor is in contact (a contact reading within the last
  :data:`CONTACT_MEMORY_FRAMES` frames), the newest contact reading is *held*: it is
  published again, with each new frame's time, as long as the frames stay within
  :data:`RELEASE_CHANGE` of the frames at the start of the hold;
* when they move away from them (the load changed: pressed harder, lifted), the hold
  ends and the network's readings pass again.

Identical frames mean an unchanged pouch, so holding is what the camera shows. The hold
also tells the health monitor the pouch is loaded (:attr:`SteadyHold.loaded`), so a
steady load is never taken for the rest state.
"""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np

from beadsight.health.stillness import change
from beadsight.inference.predictor import PressureReading

CONTACT_MEMORY_FRAMES = 15  # a contact reading this recent still counts as contact
RELEASE_CHANGE = 5.0  # frames this far from the hold's start (mean block change) end it


class SteadyHold:
    """Holds the reading of a still load (module docstring). ``enabled=False``: readings
    pass unchanged, but :attr:`loaded` is still tracked."""

    def __init__(self, enabled: bool = True, release_change: float = RELEASE_CHANGE):
        self.enabled = enabled
        self.release_change = float(release_change)
        self._held: PressureReading | None = None
        self._start: np.ndarray | None = None  # averaged thumbnail when the hold began
        self._recent: deque[PressureReading] = deque(maxlen=CONTACT_MEMORY_FRAMES)
        self._since_contact = CONTACT_MEMORY_FRAMES + 1
        self.holds = 0  # holds begun

    @property
    def holding(self) -> bool:
        return self._held is not None

    @property
    def loaded(self) -> bool:
        """In contact now or recently, or holding a still load."""
        return self.holding or self._since_contact <= CONTACT_MEMORY_FRAMES

    def reset(self) -> None:
        self._held = self._start = None
        self._recent.clear()
        self._since_contact = CONTACT_MEMORY_FRAMES + 1

    def apply(
        self, reading: PressureReading, still: bool, current: np.ndarray | None
    ) -> PressureReading:
        """The reading to publish for ``reading``. still: the frames are still now;
        current: the averaged thumbnail of the newest frames (stillness detector)."""
        self._recent.append(reading)
        self._since_contact = 0 if reading.has_contact else self._since_contact + 1
        if self._held is not None and current is not None and self._start is not None:
            if change(current, self._start) > self.release_change:
                self._held = self._start = None  # the load changed
        if self._held is None and still and current is not None:
            contact = [r for r in self._recent if r.has_contact]
            if contact:
                self._held, self._start = contact[-1], current.copy()
                self.holds += 1
        if self._held is None or not self.enabled:
            return reading
        return dataclasses.replace(
            self._held,
            timestamp_s=reading.timestamp_s,
            latency_s=reading.latency_s,
            frame_index=reading.frame_index,
            dropped_frames=reading.dropped_frames,
        )
