"""Are the frames still? Cheap frame comparison for the health monitor.

A frame is reduced to a :func:`thumbnail`: gray, area-averaged to :data:`STILL_GRID` x
:data:`STILL_GRID` blocks (each a few mm of the pouch), divided by its own mean
brightness (a slow lighting change is not motion). Camera frames shimmer (noise, JPEG
blocks, beads jittering), so :class:`StillnessDetector` compares *averages* of
:data:`STILL_FRAMES` thumbnails: the newest ones with those :data:`STILL_FRAMES` + 1
frames before. :func:`change` is their mean block difference in gray levels of a
frame of mean 128: about 2 for a still simulated pouch at 64 px, 5 and more while a
finger presses or lifts.
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

STILL_GRID = 16  # thumbnails have this many blocks per side
STILL_FRAMES = 8  # thumbnails averaged per comparison (frames)
STILL_THRESHOLD = 3.2  # mean block change of still frames (gray levels at mean 128)
_MEAN_GRAY = 128.0  # thumbnails are scaled to this mean


def thumbnail(frame_rgb: np.ndarray) -> np.ndarray:
    """frame_rgb: (H, W, 3) uint8 RGB -> (STILL_GRID, STILL_GRID) float32, mean 128."""
    gray = cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2GRAY)
    small = cv2.resize(gray, (STILL_GRID, STILL_GRID), interpolation=cv2.INTER_AREA)
    small = small.astype(np.float32)
    return small * (_MEAN_GRAY / max(float(small.mean()), 1.0))


def change(a: np.ndarray, b: np.ndarray) -> float:
    """The mean block difference of two (averaged) thumbnails (gray levels at mean 128)."""
    return float(np.abs(a - b).mean())


class StillnessDetector:
    """Still when the average of the newest ``frames`` thumbnails differs from the average
    of the ``frames`` before the one preceding them by less than ``threshold``."""

    def __init__(self, frames: int = STILL_FRAMES, threshold: float = STILL_THRESHOLD):
        if frames < 1 or not threshold > 0:
            raise ValueError(f"frames must be >= 1 and threshold > 0, got {frames}, {threshold}")
        self.frames = int(frames)
        self.threshold = float(threshold)
        self._recent: deque[np.ndarray] = deque(maxlen=2 * self.frames + 1)
        self.last_change = float("nan")  # the newest comparison's change
        self.current: np.ndarray | None = None  # average of the newest ``frames`` thumbnails

    def reset(self) -> None:
        self._recent.clear()
        self.current, self.last_change = None, float("nan")

    def update(self, thumb: np.ndarray) -> bool:
        """Add the next frame's thumbnail; True if the frames are still."""
        recent = self._recent
        recent.append(thumb)
        n = self.frames
        self.current = np.mean(list(recent)[-n:], axis=0)
        if len(recent) < recent.maxlen:
            return False
        before = np.mean(list(recent)[:n], axis=0)
        self.last_change = change(self.current, before)
        return self.last_change < self.threshold
