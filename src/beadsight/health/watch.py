"""What the sensing thread does per reading for health: stillness, the steady-load hold, rest.

:class:`SensorWatch` takes each model-input frame and its reading, and returns the reading
to publish (the :class:`~beadsight.live.hold.SteadyHold` may hold a still load) with the
newest :class:`~beadsight.health.monitor.HealthReport`. A frame is a *rest* frame (for
the :class:`~beadsight.health.monitor.HealthMonitor`) when the frames are still, the model
sees no contact and no load is held or was just seen; the monitor takes its automatic
reference only from rest frames whose force is also about zero. Per frame this costs a
16x16 thumbnail; the health figures run on rest frames, rate-limited.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from beadsight.health.monitor import HealthMonitor, HealthReport, HealthSettings
from beadsight.health.rest import RestReference
from beadsight.health.stillness import StillnessDetector, thumbnail
from beadsight.inference.predictor import PressureReading
from beadsight.live.hold import SteadyHold


class SensorWatch:
    """Stillness + hold + health for one sensor (module docstring).

    sensor_size_mm: the model's field of view; hold: hold still loads (False: readings
    pass unchanged); reference: a calibration rest reference, or None (automatic);
    background: health checks on a worker thread.
    """

    def __init__(
        self,
        sensor_size_mm: float,
        *,
        hold: bool = True,
        reference: RestReference | None = None,
        settings: HealthSettings | None = None,
        background: bool = False,
    ):
        self.stillness = StillnessDetector()
        self.hold = SteadyHold(enabled=hold)
        self.monitor = HealthMonitor(sensor_size_mm, settings, reference, background)
        self.still = False
        self.rest = False

    @classmethod
    def for_live(cls, settings: Any, sensor_size_mm: float, reference: Any) -> SensorWatch | None:
        """The watch a live sensor with these :class:`LiveSettings` runs, on a worker
        thread (None: neither health nor hold is on)."""
        if not (settings.health or settings.hold):
            return None
        return cls(sensor_size_mm, hold=settings.hold, reference=reference, background=True)

    def observe(self, frame_rgb: np.ndarray) -> bool:
        """A frame that entered the window without a reading of its own; True if still."""
        self.still = self.stillness.update(thumbnail(frame_rgb))
        return self.still

    def process(
        self, frame_rgb: np.ndarray, reading: PressureReading
    ) -> tuple[PressureReading, HealthReport]:
        """frame_rgb: (S, S, 3) uint8 RGB, the reading's newest frame -> (reading to
        publish, health report)."""
        still = self.observe(frame_rgb)
        published = self.hold.apply(reading, still, self.stillness.current)
        self.rest = still and not reading.has_contact and not self.hold.loaded
        report = self.monitor.add(frame_rgb, reading.force_n, reading.timestamp_s, self.rest)
        return published, report

    def reset(self) -> None:
        """The stream restarted (camera reopened): forget stillness and any held load."""
        self.stillness.reset()
        self.hold.reset()

    def close(self) -> None:
        self.monitor.close()
