"""Frame sources for live sensing: camera, video file, simulator, or any paced iterator.

A :class:`FrameSource` runs a background reader that keeps the newest frames with their
capture timestamps (capture never waits for the consumer); :meth:`FrameSource.read_new`
hands out the frames that arrived since the consumer's last one (at most ``limit``,
oldest first; never the same frame twice), waiting up to a timeout for one to arrive.
A consumer slower than the camera thus gets every recent frame to keep its temporal
window consecutive, and frames older than ``limit`` are skipped. Sources signal faults
with :class:`SourceDisconnected` (transient: the sensor reopens the source with
backoff) and :class:`SourceEnded` (a finite source has no more frames).

:func:`frame_converter` decides, from the first frame, how frames become the model's
input: (S, S, 3) uint8 RGB.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.errors import BeadSightError

logger = logging.getLogger(__name__)

DEFAULT_SIM_FPS = 30.0  # the reference camera's rate
MIN_TIMESTAMP_STEP_S = 1e-6  # consecutive capture timestamps differ by at least this
CAMERA_READ_SLICE_S = 0.25  # longest single wait on a camera, so close() is prompt
HISTORY_FRAMES = 64  # newest frames a paced source keeps for a consumer that fell behind


class SourceDisconnected(BeadSightError):
    """The source stopped delivering frames but may come back (camera unplugged)."""


class SourceEnded(Exception):
    """A finite source (video file, finite iterator) has delivered its last frame."""


@dataclass(frozen=True)
class SourceFrame:
    """One frame from a source.

    image: (H, W, 3) uint8 in ``channel_order``. timestamp_s: capture time, unix seconds
    (``time.time()`` clock), strictly increasing. index: position in the source's stream
    since it was opened (a gap means frames were skipped). reference_force_n: true force
    when the source knows it (the simulator), else NaN.
    """

    image: np.ndarray
    timestamp_s: float
    index: int
    channel_order: str = "BGR"
    reference_force_n: float = math.nan


class FrameSource(ABC):
    """A source of frames with a background reader; see the module docstring."""

    name: str = "source"

    @abstractmethod
    def open(self) -> None:
        """Start delivering frames (raises a DeviceError/BeadSightError if it cannot)."""

    @abstractmethod
    def read_new(self, after_index: int, timeout_s: float, limit: int = 1) -> list[SourceFrame]:
        """Frames with ``index > after_index``, oldest first, at most the ``limit`` newest,
        waiting up to ``timeout_s`` for at least one.

        Returns an empty list on timeout; raises :class:`SourceDisconnected` or
        :class:`SourceEnded` once no new frame is left.
        """

    def read_newest(self, after_index: int, timeout_s: float) -> SourceFrame | None:
        """The newest frame with ``index > after_index`` (None on timeout)."""
        frames = self.read_new(after_index, timeout_s, 1)
        return frames[-1] if frames else None

    @abstractmethod
    def close(self) -> None:
        """Stop the reader and release the device; idempotent."""

    def __enter__(self) -> FrameSource:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- paced iterators (simulator, recorded frames) ------------------------------------------
FrameItem = tuple[np.ndarray, float]  # (image, reference_force_n)


class PacedSource(FrameSource):
    """Plays frames from an iterator at ``fps`` on a background thread, like a camera.

    make_frames: called at each (re)start; returns an iterable of ``(image,
        reference_force_n)`` pairs, images (H, W, 3) uint8 in ``channel_order``.
    Frames are stamped with ``time.time()`` when published. If producing a frame takes
    longer than a period, the clock is re-anchored (the source runs slower, it does not
    burst to catch up). At the end of the iterable: restart if ``loop``, else the
    source ends.
    """

    def __init__(
        self,
        name: str,
        make_frames: Callable[[], Iterable[FrameItem]],
        fps: float,
        channel_order: str = "RGB",
        loop: bool = False,
    ):
        if not fps > 0:
            raise ValueError(f"{name}: fps must be > 0, got {fps}")
        self.name = name
        self.fps = float(fps)
        self.channel_order = channel_order
        self.loop = loop
        self._make_frames = make_frames
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._history: deque[SourceFrame] = deque(maxlen=HISTORY_FRAMES)
        self._ended: BaseException | None = None

    def open(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._history.clear()
        self._ended = None
        self._thread = threading.Thread(target=self._run, name=f"source-{self.name}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None

    def _frames(self) -> Iterator[FrameItem]:
        while True:
            produced = False
            for item in self._make_frames():
                produced = True
                yield item
            if not (self.loop and produced):
                return

    def _run(self) -> None:
        period = 1.0 / self.fps
        due = time.monotonic()
        index, last_t = 0, -math.inf
        try:
            for image, reference_force_n in self._frames():
                delay = due - time.monotonic()
                if delay > 0:
                    if self._stop.wait(delay):
                        return
                elif delay < -period:
                    due = time.monotonic()  # fell behind: re-anchor instead of bursting
                if self._stop.is_set():
                    return
                last_t = max(time.time(), last_t + MIN_TIMESTAMP_STEP_S)
                frame = SourceFrame(
                    image, last_t, index, self.channel_order, float(reference_force_n)
                )
                with self._cond:
                    self._history.append(frame)
                    self._cond.notify_all()
                index += 1
                due += period
            self._finish(SourceEnded(f"{self.name} ended after {index} frames"))
        except BaseException as e:  # the generator failed: report it to the reader
            logger.exception("%s: frame generator failed", self.name)
            self._finish(SourceDisconnected(f"{self.name}: {type(e).__name__}: {e}"))

    def _finish(self, error: BaseException) -> None:
        with self._cond:
            self._ended = error
            self._cond.notify_all()

    def read_new(self, after_index: int, timeout_s: float, limit: int = 1) -> list[SourceFrame]:
        def fresh() -> bool:
            return bool(self._history) and self._history[-1].index > after_index

        with self._cond:
            self._cond.wait_for(
                lambda: fresh() or self._ended is not None or self._stop.is_set(), timeout_s
            )
            if fresh():
                new = [f for f in self._history if f.index > after_index]
                return new[-limit:]
            if self._ended is not None:
                raise self._ended
            return []


class SimSource(PacedSource):
    """The simulated sensor (:class:`beadsight.sim.SimulatedSession`) as a live source.

    Frames are rendered at the model's image size and paced at ``fps``; each carries
    the simulator's true normal force as ``reference_force_n``.
    """

    def __init__(
        self, image_size: int, fps: float | None = None, seed: int = 0, config: Any = None
    ):
        from beadsight.sim.config import SimConfig

        base = config if config is not None else SimConfig()
        fps = float(fps or base.fps or DEFAULT_SIM_FPS)
        self.config = _replace(base, image_size_px=image_size, fps=fps)
        self.seed = seed
        super().__init__(f"sim (seed {seed})", self._session, fps, "RGB", loop=False)

    def _session(self) -> Iterator[FrameItem]:
        from beadsight.sim.session import SimulatedSession

        for record in SimulatedSession(self.config, self.seed):
            yield record.frame_rgb, record.true_force_n


def _replace(config: Any, **changes: Any) -> Any:
    import dataclasses

    return dataclasses.replace(config, **changes)


# --- cameras and video files ---------------------------------------------------------------
class CameraSource(FrameSource):
    """A :class:`beadsight.devices.base.Camera` (OpenCV camera or file, virtual camera).

    make_camera: called at each (re)open; returns an unconnected camera.
    is_file: a video file (its end is :class:`SourceEnded`, or a restart if ``loop``)
    rather than a live camera (its loss is :class:`SourceDisconnected`).
    """

    def __init__(
        self, name: str, make_camera: Callable[[], Any], is_file: bool = False, loop: bool = False
    ):
        self.name = name
        self.is_file = is_file
        self.loop = loop
        self._make_camera = make_camera
        self._camera: Any = None
        self._index_offset = 0  # keeps indices increasing across loops of a file
        self._last_index = -1
        self._last_t = -math.inf
        self._closed = threading.Event()

    def open(self) -> None:
        from beadsight.devices.base import DeviceNotConnectedError

        self._closed.clear()
        camera = None
        try:
            camera = self._make_camera()
            camera.connect()
        except DeviceNotConnectedError as e:
            if camera is not None:
                camera.close()
            raise SourceDisconnected(str(e)) from e
        self._camera = camera

    def close(self) -> None:
        self._closed.set()
        camera, self._camera = self._camera, None
        if camera is not None:
            camera.close()

    def read_new(self, after_index: int, timeout_s: float, limit: int = 1) -> list[SourceFrame]:
        """Waits for one new frame, then drains what else the camera has queued."""
        frames: list[SourceFrame] = []
        deadline = time.monotonic() + timeout_s
        while not self._closed.is_set() and self._camera is not None:
            wait = 0.0 if frames else min(deadline - time.monotonic(), CAMERA_READ_SLICE_S)
            if wait < 0:
                break
            frame = self._read_one(wait, ended_ok=bool(frames))
            if frame is None:
                if frames:
                    break  # drained
                continue
            if frame.index > after_index:
                frames.append(frame)
        return frames[-limit:]

    def _read_one(self, timeout_s: float, ended_ok: bool) -> SourceFrame | None:
        """The camera's next queued frame, or None if none came within ``timeout_s``."""
        from beadsight.devices.base import CameraDisconnectedError, DeviceTimeoutError

        try:
            frame = self._camera.read(timeout_s)
        except DeviceTimeoutError:
            return None
        except CameraDisconnectedError as e:
            if ended_ok:
                return None  # report the end on the next call, after these frames
            if not self.is_file:
                raise SourceDisconnected(e.detail) from e
            if not self.loop:
                raise SourceEnded(
                    f"{self.name} ended after {self._last_index + 1} frames"
                ) from None
            self._restart_file()
            return None
        index = self._index_offset + frame.index
        if index <= self._last_index:
            return None
        self._last_index = index
        self._last_t = max(frame.t_unix, self._last_t + MIN_TIMESTAMP_STEP_S)
        return SourceFrame(frame.image, self._last_t, index, "BGR")

    def _restart_file(self) -> None:
        logger.info("%s: end of file, looping", self.name)
        self._index_offset = self._last_index + 1
        self.close()
        self.open()


def _opencv_camera_source(
    spec: int | Path, fps: float | None, loop: bool, any_size: bool
) -> CameraSource:
    """Camera index -> a camera asked for the reference mode (1280x1024 MJPG, ``fps`` or
    30; any size if ``any_size``); path -> a video file played at its own rate."""
    from beadsight.devices.camera import OpenCVCamera

    if isinstance(spec, Path):
        if not spec.is_file():
            raise FileNotFoundError(f"{spec}: video file not found")
        return CameraSource(
            f"video {spec}",
            lambda: OpenCVCamera(str(spec), width=None, height=None, realtime=True),
            is_file=True,
            loop=loop,
        )
    kwargs: dict[str, Any] = {"fps": fps} if fps else {}
    if any_size:
        kwargs.update(width=None, height=None)
    return CameraSource(f"camera {spec}", lambda: OpenCVCamera(spec, **kwargs), is_file=False)


def open_source(
    spec: int | str | Path | FrameSource,
    image_size: int,
    fps: float | None = None,
    loop: bool = False,
    seed: int = 0,
    any_size: bool = False,
) -> FrameSource:
    """A (not yet opened) source for ``spec``: a FrameSource, ``"sim"``, a camera index
    (int or a string of digits) or a video file path.

    fps: the simulator's rate, or the rate asked of a camera (a video file plays at its
    own rate). loop: restart a video at its end. any_size: accept any camera resolution
    (when a custom preprocessing is given) instead of requiring 1280x1024.
    """
    if isinstance(spec, FrameSource):
        return spec
    if isinstance(spec, str) and spec.strip().lower() == "sim":
        return SimSource(image_size, fps=fps, seed=seed)
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        return _opencv_camera_source(int(spec), fps, loop=False, any_size=any_size)
    return _opencv_camera_source(Path(spec), fps, loop, any_size)


# --- frame -> model input --------------------------------------------------------------------
def frame_converter(
    first: SourceFrame,
    source_name: str,
    image_size: int,
    preprocess: str | Path | None = "auto",
) -> Callable[[SourceFrame], np.ndarray]:
    """How frames like ``first`` become (S, S, 3) uint8 RGB model input: the one rule of
    :func:`beadsight.inference.frames.input_converter` (``preprocess`` "auto" by default;
    None means "auto")."""
    from beadsight.inference.frames import input_converter

    convert = input_converter(
        first.image, first.channel_order, image_size, preprocess, f"source {source_name}"
    )
    return lambda frame: convert(frame.image)
