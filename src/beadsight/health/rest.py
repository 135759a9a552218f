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
* at most one rest reference per :data:`REST_REFRESH_S` of frame time;
* **not moved by a load** (the slow-load guard): a model reads a load that grows slowly
  (under about 1 N/s) as no load at all, so the rules above alone would take it into the
  rest image, second by second, until a held 7 N reads 0 N. So a rest state is also
  compared with the *anchor*, an earlier rest reference, by its local bead motion
  (:func:`~beadsight.health.flow.bead_motion`: the motion an affine drift does not
  explain, as a finger's does), and refused over :data:`SLOW_LOAD_MM`. It is not judged,
  and becomes the anchor, where a load was read since the anchor (a press leaves a new
  packing) or a reading at the contact force came within :data:`RELAX_S` (the packing
  relaxes); otherwise the anchor moves on to an accepted state every :data:`ANCHOR_S`, so
  that a drift (the camera, lighting, the beads creeping as a whole) is followed. A pouch
  that moved and then stays in its new state for :data:`SETTLE_S` while the model reads no
  load (a light object left on it, a press read under the contact force) is taken as the
  new rest state. What is left: a load that grows in unread steps with still pauses of
  :data:`SETTLE_S` between them.

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

import logging
import math
import threading
from collections import deque

import numpy as np

from beadsight.config import ContactThresholds
from beadsight.data.rest import REST_FRAMES, REST_SETTLE_FRAMES, RestReference, average_rest
from beadsight.health.flow import bead_motion, rest_gray

logger = logging.getLogger(__name__)

UNLOADED_READINGS = REST_SETTLE_FRAMES  # readings judged for "unloaded" (0.5 s at 30 fps)
REST_GUARD_FRAMES = 12  # unloaded, still frames that must follow a rest image's frames
REST_REFRESH_S = 1.0  # at most one new rest reference per this much frame time, s
# the slow-load guard (module docstring); measured on the simulator, see docs/live.md
SLOW_LOAD_MM = 0.10  # local bead motion from the anchor that refuses a rest state, mm
RELAX_S = 3.0  # rest states this soon after a reading at the contact force are not judged, s
ANCHOR_S = 10.0  # an unchanged rest state becomes the anchor after this long, s
SETTLE_S = 5.0  # a moved pouch that stays in its new state this long is at rest, s


class RestTracker:
    """Takes a rest reference whenever the pouch is unloaded and still (module docstring).

    sensor_size_mm: the side of the frames' field of view (the slow-load guard's mm);
    thresholds: :class:`~beadsight.config.ContactThresholds` (release and contact force);
    refresh_s: frame time between two rest references; have_rest: a rest reference
    already exists (a rest file), so the next one is "refreshed", not "start-up".
    """

    def __init__(
        self,
        sensor_size_mm: float,
        thresholds: ContactThresholds | None = None,
        refresh_s: float = REST_REFRESH_S,
        have_rest: bool = False,
    ):
        self.thresholds = thresholds or ContactThresholds()
        self.refresh_s = float(refresh_s)
        self.sensor_size_mm = float(sensor_size_mm)
        self.refused = 0  # rest states refused by the slow-load guard
        self._contact_s = -math.inf  # frame time of the newest reading at the contact force
        self._anchor: tuple[np.ndarray, float] | None = None  # gray, frame time
        self._moved: tuple[np.ndarray, float] | None = None  # the refused state it moved to
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
            if force_n >= self.thresholds.contact_n:
                self._contact_s = float(t_s)
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
        image = average_rest(np.stack([f for f, _ in list(self._frames)[:REST_FRAMES]]))
        taken_at_s = self._frames[REST_FRAMES - 1][1]
        self._frames.clear()
        self._last_s = t_s
        if not self._admit(rest_gray(image), float(t_s), requested):
            return None
        self.loaded_before, self.loaded_since_rest = self.loaded_since_rest, False
        origin = "requested" if requested else "refreshed" if self.taken else "start-up"
        self._requested.clear()
        self.taken += 1
        return RestReference(image, REST_FRAMES, taken_at_s, origin)

    def _admit(self, gray: np.ndarray, t_s: float, requested: bool) -> bool:
        """The slow-load guard (module docstring): may this rest state (gray, at frame time
        ``t_s``) be the rest reference?"""
        anchor = self._anchor
        if (
            anchor is None
            or requested
            or self._contact_s > anchor[1]  # a press read since the anchor: a new packing
            or t_s - self._contact_s < RELAX_S
        ):
            self._anchor, self._moved = (gray, t_s), None
            return True
        moved_mm = bead_motion(anchor[0], gray, self.sensor_size_mm).local_mm
        if moved_mm <= SLOW_LOAD_MM:
            self._moved = None
            if t_s - anchor[1] >= ANCHOR_S:
                self._anchor = (gray, t_s)
            return True
        moved = self._moved
        if moved is None or bead_motion(moved[0], gray, self.sensor_size_mm).local_mm > (
            SLOW_LOAD_MM
        ):
            if moved is None:
                logger.info(
                    "rest: not refreshed: the beads moved %.2f mm locally since the rest "
                    "state of %.1f s with no load read (a slow or light load?)",
                    moved_mm,
                    anchor[1],
                )
            self._moved = (gray, t_s)  # still moving: wait for it to stay
        elif t_s - moved[1] >= SETTLE_S:  # it stayed in its new state: at rest there
            logger.info(
                "rest: the pouch moved %.2f mm locally with no load read and stayed so for "
                "%.0f s: taken as the rest state",
                moved_mm,
                t_s - moved[1],
            )
            self._anchor, self._moved = (gray, t_s), None
            return True
        self.refused += 1
        return False

    def reset(self) -> None:
        """The stream restarted: forget the frames and readings seen (not what was taken)."""
        self._frames.clear()
        self._recent.clear()
