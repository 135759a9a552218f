"""Achieved rate and latency percentiles of live sensing, over a sliding window."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from beadsight.live.settings import NO_SIGNAL_AFTER_S

STATS_WINDOW_S = 5.0  # achieved rate and latency percentiles cover this recent span


@dataclass(frozen=True)
class LiveStats:
    """Rates and latencies over the last :data:`STATS_WINDOW_S` (latencies in seconds).

    latency: capture -> reading available; inference: the predictor's own time.
    rate_hz: readings per second; source_rate_hz: frames per second from the source.
    When inference is slower than the camera, the frames that arrived meanwhile enter
    the window without a reading of their own (rate_hz < source_rate_hz) so the window
    stays consecutive; skipped_frames: frames that never entered the window (more than
    a window behind); dropped_frames: gaps the predictor saw in the capture timestamps
    (frames the camera itself lost, plus skipped ones).
    """

    readings: int
    frames: int  # frames taken from the source (each entered the window)
    rate_hz: float
    source_rate_hz: float
    latency_p50_s: float
    latency_p99_s: float
    inference_p50_s: float
    inference_p99_s: float
    skipped_frames: int
    dropped_frames: int
    # camera truth, per source (beadsight.devices.truth; NaN/0 for sources that do not tell)
    camera_dropped: int = 0  # frames the camera lost (capture-time gaps)
    camera_duplicated: int = 0  # frames identical to the one before
    camera_fps: float = math.nan  # the rate the camera delivers (last 2 s)
    requested_fps: float = math.nan  # the rate asked of it
    camera_slow: bool = False  # camera_fps below 90 % of requested_fps

    def summary(self) -> str:
        def ms(v: float) -> str:
            return "-" if math.isnan(v) else f"{v * 1e3:.1f}"

        return (
            f"{self.rate_hz:.1f} Hz (source {self.source_rate_hz:.1f} Hz), latency p50 "
            f"{ms(self.latency_p50_s)} ms p99 {ms(self.latency_p99_s)} ms, inference p50 "
            f"{ms(self.inference_p50_s)} ms p99 {ms(self.inference_p99_s)} ms, "
            f"{self.readings} readings, skipped {self.skipped_frames}, "
            f"dropped {self.dropped_frames}; camera {self.camera_fps:.1f} of "
            f"{self.requested_fps:.3g} fps{' (SLOW)' if self.camera_slow else ''}, "
            f"dropped {self.camera_dropped}, duplicated {self.camera_duplicated}"
        )

    def with_camera(self, camera: Any) -> LiveStats:
        """These stats with a camera's truth (its ``stats``: a
        :class:`~beadsight.devices.camera.CameraStats`); unchanged for sources without."""
        cam = getattr(camera, "stats", None)
        if not hasattr(cam, "duplicated"):
            return self
        return dataclasses.replace(
            self,
            camera_dropped=cam.dropped,
            camera_duplicated=cam.duplicated,
            camera_fps=cam.delivered_fps,
            requested_fps=cam.requested_fps,
            camera_slow=cam.slow,
        )


class RateMeter:
    """Sliding-window rate and latency percentiles; thread-safe."""

    def __init__(self, window_s: float = STATS_WINDOW_S, stale_after_s: float = NO_SIGNAL_AFTER_S):
        self.window_s = window_s
        self.stale_after_s = stale_after_s  # no event for this long: the rate is 0
        self._lock = threading.Lock()
        self._readings: deque[tuple[float, float, float]] = deque()  # (done, latency, infer)
        self._frames: deque[float] = deque()  # arrival times of source frames
        self.count = 0
        self.frames = 0
        self.skipped = 0
        self.dropped = 0

    def _trim(self, now: float) -> None:
        while self._readings and self._readings[0][0] < now - self.window_s:
            self._readings.popleft()
        while self._frames and self._frames[0] < now - self.window_s:
            self._frames.popleft()

    def add_frames(self, now: float, count: int, skipped: int) -> None:
        with self._lock:
            self._frames.extend([now] * count)
            self.frames += count
            self.skipped += skipped
            self._trim(now)

    def add_reading(self, now: float, latency_s: float, inference_s: float, dropped: int) -> None:
        with self._lock:
            self._readings.append((now, latency_s, inference_s))
            self.count += 1
            self.dropped = dropped
            self._trim(now)

    def _rate(self, times: list[float], now: float) -> float:
        if len(times) < 2 or now - times[-1] > self.stale_after_s:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    def snapshot(self) -> LiveStats:
        now = time.monotonic()
        with self._lock:
            self._trim(now)
            rows = np.array(self._readings, dtype=np.float64).reshape(-1, 3)
            arrivals = list(self._frames)
            count, frames, skipped, dropped = self.count, self.frames, self.skipped, self.dropped
        if len(rows):
            lat = np.percentile(rows[:, 1], [50, 99])
            inf = np.percentile(rows[:, 2], [50, 99])
        else:
            lat = inf = (math.nan, math.nan)
        return LiveStats(
            readings=count,
            frames=frames,
            rate_hz=self._rate(list(rows[:, 0]), now),
            source_rate_hz=self._rate(arrivals, now),
            latency_p50_s=float(lat[0]),
            latency_p99_s=float(lat[1]),
            inference_p50_s=float(inf[0]),
            inference_p99_s=float(inf[1]),
            skipped_frames=skipped,
            dropped_frames=dropped,
        )
