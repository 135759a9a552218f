"""A virtual camera: frames rendered on demand at a fixed rate in simulated time.

:class:`VirtualCamera` has the same interface as
:class:`~beadsight.devices.camera.OpenCVCamera` (it shares its reader thread, queue,
``read`` / ``read_latest`` and frame accounting) but its frames come from a render
function, typically the rig's simulated pouch under the virtual finger. Requesting a
size the renderer does not produce fails exactly like a real camera that refuses a mode.

Faults (thread-safe): :meth:`unplug` (capture stops; ``read`` raises
CameraDisconnectedError once the queue is empty) and :meth:`stall` (no frames for a
while; the reader counts the gap as dropped frames).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from beadsight.devices.camera import DEFAULT_FPS, DEFAULT_QUEUE_FRAMES, BufferedCamera, verify_mode
from beadsight.devices.virtual.clock import SimClock

logger = logging.getLogger(__name__)


class VirtualCamera(BufferedCamera):
    """Frames from ``render_fn() -> (H, W, 3) uint8 BGR`` at ``fps`` (simulated time).

    width, height: requested size (px), verified against the rendered frames; None
    accepts the renderer's size.
    """

    def __init__(
        self,
        render_fn: Callable[[], np.ndarray],
        width: int | None = None,
        height: int | None = None,
        fps: float = DEFAULT_FPS,
        *,
        clock: SimClock | None = None,
        time_scale: float = 1.0,
        queue_frames: int = DEFAULT_QUEUE_FRAMES,
        name: str = "virtual camera",
    ):
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        super().__init__(name, queue_frames=queue_frames, live=True)
        self.render_fn = render_fn
        self.requested = (width, height)
        self.requested_fps = float(fps)
        self.clock = clock if clock is not None else SimClock(time_scale)
        self._lock = threading.Lock()
        self._unplugged = False
        self._stall_s = 0.0
        self._next_t: float | None = None
        self._first: np.ndarray | None = None

    # --- faults -------------------------------------------------------------------------
    def unplug(self) -> None:
        """Simulate pulling the USB cable: no frame after the one being captured."""
        with self._lock:
            self._unplugged = True

    def stall(self, seconds: float) -> None:
        """Deliver no frames for ``seconds`` (simulated), like a USB hiccup."""
        with self._lock:
            self._stall_s += float(seconds)

    # --- BufferedCamera hooks -----------------------------------------------------------
    def _open(self) -> tuple[int, int, float]:
        with self._lock:
            self._unplugged = False
        first = self._render()
        height, width = first.shape[:2]
        verify_mode(
            self.name, self.requested, (width, height), "the virtual camera renders a fixed size"
        )
        self._first = first
        self._next_t = None
        # frames per *host* second: what the reader's timestamps and gap accounting see
        return width, height, self.requested_fps * self.clock.time_scale

    def _grab(self) -> np.ndarray | None:
        with self._lock:
            if self._unplugged:
                self._end_reason = "stopped delivering frames (unplugged)"
                return None
            stall, self._stall_s = self._stall_s, 0.0
        now = self.clock.now()
        if self._next_t is None:
            self._next_t = now
        period_s = 1.0 / self.requested_fps  # simulated
        self._next_t = max(self._next_t, now - period_s) + stall
        if not self.clock.wait_until(self._next_t, self._stop):
            return None
        self._next_t += period_s
        if self._first is not None:
            image, self._first = self._first, None
            return image
        return self._render()

    def _render(self) -> np.ndarray:
        image = np.asarray(self.render_fn())
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(
                f"{self.name}: render_fn must return (H, W, 3) uint8, got {image.dtype} {image.shape}"
            )
        return image
