"""Virtual cameras: frames rendered or played at a fixed rate, the real cameras' interface.

* :class:`VirtualCamera` - frames from a render function, typically the virtual rig's
  simulated pouch under the virtual finger, on the rig's simulated clock.
* :class:`PlaybackCamera` - frames (and, optionally, the true force of each) from an
  iterable: recorded frames, a test's script; it ends after the last or loops.
* :class:`SimCamera` - the simulated sensor (:class:`beadsight.sim.SimulatedSession`)
  as a camera: RGB frames at the model's size with the true force of each.

All are :class:`~beadsight.devices.camera.BufferedCamera` objects, like
:class:`~beadsight.devices.opencv.OpenCVCamera`: the same reader thread, reads, frame
accounting and errors. ``realtime=False`` plays as fast as the frames are read instead
of at ``fps``. Requesting a size the renderer does not produce fails exactly like a real
camera that refuses a mode.

Faults (thread-safe): :meth:`VirtualCamera.unplug` (capture stops; reads raise
CameraDisconnectedError once the queue is empty; :meth:`~BufferedCamera.connect` plugs
it back in), :meth:`VirtualCamera.stall` (no frames for a while; the reader counts
the gap as dropped frames), :meth:`VirtualCamera.drop` (lose the next frames, like a
USB bus that lost them), :meth:`VirtualCamera.duplicate` (hand out the previous image
again instead of the next frames, like a driver re-reading its last buffer) and
:meth:`VirtualCamera.deliver_at` (run slower than the fps it claims, like OpenCV's V4L2
backend on some cameras).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import numpy as np

from beadsight.devices.camera import DEFAULT_FPS, DEFAULT_QUEUE_FRAMES, BufferedCamera, Captured
from beadsight.devices.clock import SimClock

logger = logging.getLogger(__name__)

PlayedFrame = np.ndarray | tuple[np.ndarray, float]  # an image, or (image, true force in N)


class VirtualCamera(BufferedCamera):
    """Frames from ``render_fn() -> (H, W, 3) uint8`` at ``fps`` (simulated time).

    width, height: requested size (px), verified against the rendered frames; None
    accepts the renderer's size. channel_order: of the rendered images ("BGR" like a
    real camera, or "RGB"). clock / time_scale: the simulated clock the frames are
    paced on (a virtual rig passes its own).
    """

    def __init__(
        self,
        render_fn: Callable[[], np.ndarray] | None,
        width: int | None = None,
        height: int | None = None,
        fps: float = DEFAULT_FPS,
        *,
        clock: SimClock | None = None,
        time_scale: float = 1.0,
        channel_order: str = "BGR",
        realtime: bool = True,
        queue_frames: int = DEFAULT_QUEUE_FRAMES,
        name: str = "virtual camera",
    ):
        if not fps > 0:
            raise ValueError(f"{name}: fps must be > 0, got {fps}")
        if channel_order not in ("BGR", "RGB"):
            raise ValueError(f"{name}: channel_order must be 'BGR' or 'RGB', got {channel_order!r}")
        super().__init__(
            name,
            (width, height),
            queue_frames=queue_frames,
            live=realtime,
            paced=realtime,
            clock=clock if clock is not None else SimClock(time_scale),
        )
        self.render_fn = render_fn
        self.requested_fps = float(fps)
        self.channel_order = channel_order
        self._lock = threading.Lock()
        self._unplugged = False
        self._stall_s = 0.0
        self._duplicates = 0  # the next this many frames repeat the previous image
        self._last_image: np.ndarray | None = None
        self._deliver_fps: float | None = None  # the rate really delivered (None: fps)

    # --- faults -------------------------------------------------------------------------
    def unplug(self) -> None:
        """Simulate pulling the USB cable: no frame after the one being captured, even
        during a stall (reconnecting plugs it back in)."""
        with self._lock:
            self._unplugged = True
            self._end("stopped delivering frames (unplugged)")
            self._stop.set()  # the reader ends now, not after its current wait

    def stall(self, seconds: float) -> None:
        """Deliver no frames for ``seconds`` (simulated), like a USB hiccup."""
        with self._lock:
            self._stall_s += float(seconds)

    def drop(self, frames: int) -> None:
        """Lose the next ``frames`` frames (their time passes without a capture)."""
        self.stall(frames / self.requested_fps)

    def duplicate(self, frames: int) -> None:
        """Deliver the previous image again as the next ``frames`` frames."""
        with self._lock:
            self._duplicates += int(frames)

    def deliver_at(self, fps: float | None) -> None:
        """Deliver ``fps`` frames per second while claiming :attr:`requested_fps` (None:
        deliver what is claimed)."""
        if fps is not None and not 0 < fps:
            raise ValueError(f"{self.name}: deliver_at fps must be > 0, got {fps}")
        with self._lock:
            self._deliver_fps = fps

    # --- BufferedCamera hooks -----------------------------------------------------------
    def _open(self) -> float:
        with self._lock:
            self._unplugged = False
        # frames per *host* second: what the reader's timestamps and gap accounting see
        return self.requested_fps * self.clock.time_scale

    def _pace_delay_s(self) -> float:
        with self._lock:
            stall, self._stall_s = self._stall_s, 0.0
            if self._deliver_fps is not None:  # each frame comes this much later
                stall += max(1.0 / self._deliver_fps - 1.0 / self.requested_fps, 0.0)
        return stall

    def _grab(self) -> Captured | None:
        with self._lock:
            if self._unplugged:
                return self._end("stopped delivering frames (unplugged)")
            if self._duplicates > 0 and self._last_image is not None:
                self._duplicates -= 1
                return self._last_image.copy(), math.nan
        captured = self._next_frame()
        if captured is not None:
            self._last_image = captured[0]
        return captured

    def _next_frame(self) -> Captured | None:
        return self.render_fn(), math.nan

    def _mode_hint(self) -> str:
        return "the virtual camera renders a fixed size"


class PlaybackCamera(VirtualCamera):
    """Plays the frames of ``make_frames()`` at ``fps``, like a camera.

    make_frames: called at each connect (and each loop); returns an iterable of images
        (H, W, 3) uint8 in ``channel_order``, or of ``(image, reference_force_n)`` pairs.
    loop: start again after the last frame (indices keep counting up); otherwise the
        camera ends (:class:`~beadsight.devices.CameraEndedError`) after it.
    """

    def __init__(
        self,
        make_frames: Callable[[], Iterable[PlayedFrame]],
        fps: float = DEFAULT_FPS,
        *,
        channel_order: str = "RGB",
        loop: bool = False,
        name: str = "playback",
        **options: Any,
    ):
        super().__init__(None, fps=fps, channel_order=channel_order, name=name, **options)
        self.make_frames = make_frames
        self.loop = loop
        self._items: Iterator[PlayedFrame] | None = None
        self._played = 0  # frames of the current pass

    def _open(self) -> float:
        self._items, self._played = iter(self.make_frames()), 0
        return super()._open()

    def _next_frame(self) -> Captured | None:
        item = next(self._items, None)
        if item is None and self.loop and self._played > 0:
            self._items, self._played = iter(self.make_frames()), 0
            item = next(self._items, None)
        if item is None:
            return self._end("ended", finite=True)
        self._played += 1
        if isinstance(item, tuple):
            image, force_n = item
            return image, float(force_n)
        return item, math.nan

    def _release(self) -> None:
        close = getattr(self._items, "close", None)  # a generator: run its cleanup now
        self._items = None
        if close is not None:
            close()


class SimCamera(PlaybackCamera):
    """The simulated sensor as a camera: presses of a :class:`~beadsight.sim.SimulatedSession`.

    Frames are (S, S, 3) uint8 RGB at ``image_size`` px, paced at ``fps`` (default: the
    simulator's, 30); each carries the simulator's true normal force as
    ``reference_force_n``. presses: None for an endless session of random presses, that
    many presses, or a sequence of :class:`~beadsight.sim.press.Press` (a scripted
    session), after which the camera ends (``loop`` plays them again). drift: a
    :class:`~beadsight.sim.drift.DriftSpec` (or its ``--sim-drift`` text) applied to the
    frames, timed from the session's first frame.
    """

    def __init__(
        self,
        image_size: int,
        fps: float | None = None,
        seed: int = 0,
        config: Any = None,
        *,
        presses: int | Sequence[Any] | None = None,
        drift: Any = None,
        **options: Any,
    ):
        from beadsight.sim.config import SimConfig
        from beadsight.sim.drift import parse_drift

        base = config if config is not None else SimConfig()
        fps = float(fps or base.fps or DEFAULT_FPS)
        self.config = dataclasses.replace(base, image_size_px=image_size, fps=fps)
        self.seed = seed
        self.presses = presses
        self.drift = parse_drift(drift)
        options.setdefault("name", f"sim (seed {seed})")
        super().__init__(self._session, fps, channel_order="RGB", **options)

    def _session(self) -> Iterator[tuple[np.ndarray, float]]:
        from beadsight.sim.drift import DriftRenderer
        from beadsight.sim.session import SimulatedSession

        drift = DriftRenderer(self.drift, self.config.image_size_px, self.config.sensor_size_mm)
        start_s = None
        for record in SimulatedSession(self.config, self.seed, self.presses):
            start_s = record.timestamp_s if start_s is None else start_s
            yield drift.apply(record.frame_rgb, record.timestamp_s - start_s), record.true_force_n
