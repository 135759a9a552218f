"""Camera truth: what a camera really delivers, counted per camera.

:class:`FrameTruth` sees every captured frame on the reader thread and counts
*duplicated* frames (content identical to the previous frame - a driver handing out its
last buffer again) and measures the *delivered* rate over the last
:data:`RATE_WINDOW_S` against the *requested* one; below :data:`SLOW_FRACTION` of it
(OpenCV's V4L2 backend does this with some cameras) it warns once in the log and
:attr:`slow` says so until the rate recovers. Dropped frames (capture-time gaps) are
counted by :class:`~beadsight.devices.camera.BufferedCamera` itself.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

logger = logging.getLogger(__name__)

RATE_WINDOW_S = 2.0  # the delivered rate is measured over this recent span (host s)
SLOW_FRACTION = 0.9  # a camera delivering less than this fraction of its requested rate is slow


class FrameTruth:
    """Duplicate and rate accounting of one camera's frames (module docstring)."""

    def __init__(self, name: str):
        self.name = name
        self.requested_fps = 0.0
        self.duplicated = 0
        self.slow = False
        self._previous: np.ndarray | None = None
        self._times: deque[float] = deque()

    def restart(self, requested_fps: float) -> None:
        """A new stream (connect): forget the previous frame and the rate window."""
        self.requested_fps = float(requested_fps)
        self._previous = None
        self._times.clear()

    def add(self, image: np.ndarray, t_mono: float) -> bool:
        """One captured frame at host time ``t_mono``; True if it duplicates the last."""
        duplicate = self._previous is not None and np.array_equal(image, self._previous)
        if duplicate:
            self.duplicated += 1
            if self.duplicated == 1 or self.duplicated % 100 == 0:
                logger.warning("%s: %d duplicated frame(s)", self.name, self.duplicated)
        self._previous = image
        times = self._times
        times.append(t_mono)
        while times and times[0] < t_mono - RATE_WINDOW_S:
            times.popleft()
        self._judge_rate()
        return duplicate

    @property
    def delivered_fps(self) -> float:
        """Frames per second over the last :data:`RATE_WINDOW_S` (NaN: too few frames)."""
        times = self._times
        if len(times) < 3 or times[-1] - times[0] < RATE_WINDOW_S / 2:
            return float("nan")
        return (len(times) - 1) / (times[-1] - times[0])

    def _judge_rate(self) -> None:
        rate = self.delivered_fps
        if not rate == rate or self.requested_fps <= 0:
            return
        slow = rate < SLOW_FRACTION * self.requested_fps
        if slow and not self.slow:
            logger.warning(
                "%s: delivers %.1f fps but %.3g fps was requested (below %d %%)",
                self.name,
                rate,
                self.requested_fps,
                round(SLOW_FRACTION * 100),
            )
        self.slow = slow
