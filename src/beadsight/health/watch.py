"""What the sensing thread does per reading for health: stillness, rest, drift.

:class:`SensorWatch` takes each model-input frame and its reading and returns the newest
:class:`~beadsight.health.monitor.HealthReport`. A frame is a *rest* frame (for the
:class:`~beadsight.health.monitor.HealthMonitor`) when the frames are still and the model
read no contact in the last :data:`CONTACT_MEMORY_FRAMES` readings; the monitor takes its
automatic reference only from rest frames whose force is also about zero. Per frame this
costs a 16x16 thumbnail; the health figures run on rest frames, rate-limited.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from beadsight.health.monitor import HealthMonitor, HealthReport, HealthSettings
from beadsight.health.rest import RestReference
from beadsight.health.stillness import StillnessDetector, thumbnail
from beadsight.inference.predictor import PressureReading

CONTACT_MEMORY_FRAMES = 15  # a contact reading this recent still counts as loaded


class SensorWatch:
    """Stillness + health for one sensor (module docstring).

    sensor_size_mm: the model's field of view; reference: a calibration rest reference, or
    None (automatic); background: health checks on a worker thread.
    """

    def __init__(
        self,
        sensor_size_mm: float,
        *,
        reference: RestReference | None = None,
        settings: HealthSettings | None = None,
        background: bool = False,
    ):
        self.stillness = StillnessDetector()
        self.monitor = HealthMonitor(sensor_size_mm, settings, reference, background)
        self.still = False
        self.rest = False
        self._since_contact = CONTACT_MEMORY_FRAMES + 1

    @classmethod
    def for_live(cls, settings: Any, sensor_size_mm: float, reference: Any) -> SensorWatch | None:
        """The watch a live sensor with these :class:`LiveSettings` runs, on a worker
        thread (None: health is off)."""
        if not settings.health:
            return None
        return cls(sensor_size_mm, reference=reference, background=True)

    @property
    def loaded(self) -> bool:
        """The model read contact in the last :data:`CONTACT_MEMORY_FRAMES` readings."""
        return self._since_contact <= CONTACT_MEMORY_FRAMES

    def observe(self, frame_rgb: np.ndarray) -> bool:
        """A frame that entered the window without a reading of its own; True if still."""
        self.still = self.stillness.update(thumbnail(frame_rgb))
        return self.still

    def process(self, frame_rgb: np.ndarray, reading: PressureReading) -> HealthReport:
        """frame_rgb: (S, S, 3) uint8 RGB, the reading's newest frame -> health report."""
        still = self.observe(frame_rgb)
        self._since_contact = 0 if reading.has_contact else self._since_contact + 1
        self.rest = still and not self.loaded
        return self.monitor.add(frame_rgb, reading.force_n, reading.timestamp_s, self.rest)

    def reset(self) -> None:
        """The stream restarted (camera reopened): forget stillness and recent contact."""
        self.stillness.reset()
        self._since_contact = CONTACT_MEMORY_FRAMES + 1

    def close(self) -> None:
        self.monitor.close()
