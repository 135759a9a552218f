"""Taking the rest reference: which frames show the pouch unloaded and still.

A :class:`~beadsight.data.rest.RestReference` is the average of
:data:`~beadsight.data.rest.REST_FRAMES` frames of the pouch at rest (the one averaging
rule, :func:`~beadsight.data.rest.average_rest`). :class:`RestTracker` decides, frame by
frame, when to take one:

* **unloaded**: over the last :data:`UNLOADED_READINGS` readings the model read at most
  the release force (:class:`~beadsight.config.ContactThresholds`, 10 g) in the median
  and never the contact force (50 g): a model's reading of the unloaded pouch jitters
  (the GPU-trained sim model: median 0.03 N, 10 % of readings over 0.16 N), a load
  does not come and go frame by frame. Before the first reading (a rest-referenced model
  has none until it has a rest image) no frame is known to be loaded, so at start-up
  still frames alone count;
* **still**: :class:`~beadsight.health.stillness.StillnessDetector`;
* **settled**: the rest image's frames are followed by :data:`REST_GUARD_FRAMES` more
  unloaded, still frames, so the first frames of a press (not yet read as a load, not yet
  seen as motion) never enter a rest image;
* at most one rest reference per :data:`REST_REFRESH_S` of frame time.

On request (:meth:`RestTracker.request`: the user or robot knows the pouch is unloaded, e.g.
the gripper is open) the next still frames are taken whatever the readings say: the way
out of a stale rest image (the pouch bumped or re-seated), which reads as a load that
would otherwise never end.

A steady load is never unloaded, so it is never taken for the rest state, however still.
With each new reference the tracker says whether the pouch was loaded since the previous
one (:attr:`RestTracker.loaded_before`), which the health monitor needs to tell drift
from the new packing a press leaves.
"""

from __future__ import annotations

import math
import threading
from collections import deque

import cv2
import numpy as np

from beadsight.config import ContactThresholds
from beadsight.data.rest import REST_FRAMES, REST_SETTLE_FRAMES, RestReference, average_rest

REST_PX = 64  # rest images are compared at this size (px per side)
UNLOADED_READINGS = REST_SETTLE_FRAMES  # readings judged for "unloaded" (0.5 s at 30 fps)
REST_GUARD_FRAMES = 12  # unloaded, still frames that must follow a rest image's frames
REST_REFRESH_S = 1.0  # at most one new rest reference per this much frame time, s


def rest_gray(image_rgb: np.ndarray) -> np.ndarray:
    """image_rgb: (H, W, 3) uint8 RGB -> (REST_PX, REST_PX) float32 gray 0..255."""
    gray = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(gray, (REST_PX, REST_PX), interpolation=cv2.INTER_AREA).astype(np.float32)


class RestTracker:
    """Takes a rest reference whenever the pouch is unloaded and still (module docstring).

    thresholds: :class:`~beadsight.config.ContactThresholds` (release and contact force);
    refresh_s: frame time between two rest references; have_rest: a rest reference
    already exists (a rest file), so the next one is "refreshed", not "start-up".
    """

    def __init__(
        self,
        thresholds: ContactThresholds | None = None,
        refresh_s: float = REST_REFRESH_S,
        have_rest: bool = False,
    ):
        self.thresholds = thresholds or ContactThresholds()
        self.refresh_s = float(refresh_s)
        self.taken = 1 if have_rest else 0  # rest references taken (or given)
        self.loaded_since_rest = False  # a reading above the release force since the last
        self.loaded_before = False  # ... before the newest rest reference was taken
        self._recent: deque[float] = deque(maxlen=UNLOADED_READINGS)  # newest readings, N
        self._readings = 0  # readings seen since start (none: start-up)
        self._frames: deque[tuple[np.ndarray, float]] = deque(
            maxlen=REST_FRAMES + REST_GUARD_FRAMES
        )
        self._last_s = -math.inf
        self._requested = threading.Event()

    @property
    def unloaded(self) -> bool:
        """The newest :data:`UNLOADED_READINGS` readings: median at most the release force,
        none at the contact force."""
        recent = self._recent
        if len(recent) < UNLOADED_READINGS:
            return False
        median = float(np.median(recent))
        return median <= self.thresholds.release_n and max(recent) < self.thresholds.contact_n

    def request(self) -> None:
        """Take the next rest reference from the next still frames, whatever the readings
        (the caller knows the pouch is unloaded). Safe to call from any thread."""
        self._requested.set()

    @property
    def requested(self) -> bool:
        """A requested rest reference has not been taken yet."""
        return self._requested.is_set()

    def add(
        self, frame_rgb: np.ndarray, t_s: float, still: bool, force_n: float | None
    ) -> RestReference | None:
        """One frame (``force_n``: its reading, N, or None for a frame without one) at
        frame time ``t_s``; ``still``: the frames are still. Returns a new rest reference
        when this frame completes one, else None."""
        if force_n is not None:
            self._readings += 1
            self._recent.append(float(force_n))
            if not self.unloaded:
                self.loaded_since_rest = True
        requested = self._requested.is_set()
        startup = self._readings == 0 and self.taken == 0
        if not (still and (requested or self.unloaded or startup)):
            self._frames.clear()
            return None
        self._frames.append((frame_rgb.copy(), float(t_s)))
        if len(self._frames) < self._frames.maxlen:
            return None
        if not requested and t_s - self._last_s < self.refresh_s:
            return None
        frames = [f for f, _ in list(self._frames)[:REST_FRAMES]]
        taken_at_s = self._frames[REST_FRAMES - 1][1]
        self._frames.clear()
        self._last_s = t_s
        self.loaded_before, self.loaded_since_rest = self.loaded_since_rest, False
        origin = "requested" if requested else "refreshed" if self.taken else "start-up"
        self._requested.clear()
        self.taken += 1
        return RestReference(average_rest(np.stack(frames)), REST_FRAMES, taken_at_s, origin)

    def reset(self) -> None:
        """The stream restarted: forget the frames and readings seen (not what was taken)."""
        self._frames.clear()
        self._recent.clear()
