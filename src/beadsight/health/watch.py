"""What the sensing thread runs per frame for the rest reference and health.

:class:`SensorWatch` takes each model-input frame (with its reading, where it has one):
it keeps the stillness detector and the :class:`~beadsight.health.rest.RestTracker`
going, hands each new rest reference to ``on_rest`` (the live sensor gives it to its
predictor) and to the :class:`~beadsight.health.monitor.HealthMonitor`, and returns the
newest :class:`~beadsight.health.monitor.HealthReport`. Per frame this costs a 16x16
thumbnail; a frame at rest is also copied (the rest image's frames), and the health
figures run once per rest reference, on the monitor's thread.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from beadsight.config import ContactThresholds
from beadsight.data.rest import RestReference
from beadsight.health.monitor import HealthMonitor, HealthReport, HealthSettings
from beadsight.health.rest import RestTracker
from beadsight.health.stillness import StillnessDetector, thumbnail
from beadsight.inference.predictor import PressureReading

logger = logging.getLogger(__name__)

REST_WAIT_WARN_S = 3.0  # no rest reference this long after the first frame: say why

WAITING = HealthReport(
    "unknown",
    "no rest reference yet: waiting for the pouch to be unloaded and still (lift any load; "
    "or start with a stored rest, --rest FILE)",
    {},
    "none",
)


class SensorWatch:
    """Stillness, the rest reference and health for one sensor (module docstring).

    sensor_size_mm: the model's field of view. reference: a stored rest reference (a rest
    file; its image is the model's rest until the pouch is next unloaded and still), or
    None. settings: :class:`HealthSettings`. health: run the health monitor (False: only
    the rest reference is kept). background: health checks on a worker thread. on_rest:
    called with each new rest reference, on the caller's thread. thresholds: the release
    and contact forces that tell an unloaded pouch (default: 10 g and 50 g).
    """

    def __init__(
        self,
        sensor_size_mm: float,
        *,
        reference: RestReference | None = None,
        settings: HealthSettings | None = None,
        health: bool = True,
        background: bool = False,
        on_rest: Callable[[RestReference], None] | None = None,
        thresholds: ContactThresholds | None = None,
    ):
        settings = settings or HealthSettings()
        self.stillness = StillnessDetector()
        self.tracker = RestTracker(
            sensor_size_mm, thresholds, settings.rest_refresh_s, reference is not None
        )
        self.monitor = (
            HealthMonitor(sensor_size_mm, settings, reference, background) if health else None
        )
        self.on_rest = on_rest
        self.rest = reference  # the newest rest reference
        self.still = False
        self.note: HealthReport | None = None  # shown until the first check (see report)
        self._first_s = math.nan  # frame time of the first frame
        self._warned = False  # the start-up warning (waiting, or loaded) was given

    @property
    def report(self) -> HealthReport:
        """The newest health report; before the first rest state is checked, what the
        sensor waits for (:attr:`note`, else :data:`WAITING`)."""
        if self.monitor is not None and self.monitor.checks:
            return self.monitor.report
        return self.note or WAITING

    def observe(self, frame_rgb: np.ndarray, t_s: float) -> None:
        """A frame without a reading (it only entered the window, or the model has no
        rest image yet) at frame time ``t_s``."""
        self._frame(frame_rgb, t_s, None)

    def process(self, frame_rgb: np.ndarray, reading: PressureReading) -> HealthReport:
        """frame_rgb: (S, S, 3) uint8 RGB, the reading's newest frame -> health report."""
        if self.rest is not None and self.rest.origin == "file" and not self._warned:
            self._warned = True  # the first reading against a stored rest
            if reading.has_contact:
                self._loaded_at_start(reading.force_n)
        self._frame(frame_rgb, reading.timestamp_s, reading.force_n)
        return self.report

    def _loaded_at_start(self, force_n: float) -> None:
        message = (
            f"loaded at start-up: {force_n:.2f} N against the stored rest reference; readings "
            "use it until the pouch is unloaded and still, then a new rest reference is taken"
        )
        logger.warning("rest: the pouch is %s", message)
        self.note = HealthReport("unknown", message, {}, "file")

    def _frame(self, frame_rgb: np.ndarray, t_s: float, force_n: float | None) -> None:
        self.still = self.stillness.update(thumbnail(frame_rgb))
        rest = self.tracker.add(frame_rgb, t_s, self.still, force_n)
        if math.isnan(self._first_s):
            self._first_s = t_s
        if rest is None:
            if self.rest is None and not self._warned and t_s - self._first_s > REST_WAIT_WARN_S:
                self._warned = True
                logger.warning(
                    "rest: no rest reference %.0f s after start-up: the pouch has not been "
                    "unloaded and still (is it pressed or moving?); lift the load and keep it "
                    "still, or start with a stored rest (--rest FILE)",
                    REST_WAIT_WARN_S,
                )
            return
        if rest.origin == "start-up":
            logger.info(
                "rest: reference taken at start-up from %d still frames (keep the pouch "
                "unloaded when sensing starts: a load then is taken for the rest); it is "
                "refreshed whenever the pouch is unloaded and still",
                rest.frames,
            )
        self.rest = rest
        self.note = None
        if self.on_rest is not None:
            self.on_rest(rest)
        if self.monitor is not None:
            self.monitor.add(rest, self.tracker.loaded_before)

    def request_rest(self) -> None:
        """Take the next still frames as the rest reference, whatever the readings (the
        pouch is said to be unloaded). Safe to call from any thread."""
        self.tracker.request()
        logger.info("rest: a new rest reference was asked for; taken from the next still frames")

    def reset(self) -> None:
        """The stream restarted (camera reopened): forget stillness and recent readings."""
        self.stillness.reset()
        self.tracker.reset()

    def close(self) -> None:
        if self.monitor is not None:
            self.monitor.close()
