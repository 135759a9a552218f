"""Cameras with a background reader: OpenCV devices and video files, plus the shared base.

:class:`BufferedCamera` runs one reader thread per camera. Each captured frame gets its
capture timestamps (monotonic and wall clock, taken as the capture call returns) and a
capture index, and goes into a bounded queue (for :meth:`~BufferedCamera.read`, every
frame in order) and into the "latest" slot (for :meth:`~BufferedCamera.read_latest`).

Frame accounting (:attr:`BufferedCamera.stats`):

* ``dropped``: frames the *device* lost, from timestamp gaps: a gap ``dt > 1.5 / fps``
  between consecutive captures counts ``max(1, round(dt * fps) - 1)`` frames (live
  devices only; a file cannot lose frames).
* ``overflowed``: frames pushed out of the full queue because ``read`` fell behind
  (live devices; files wait for the reader instead).
* ``skipped``: frames ``read_latest`` passed over on purpose to return the newest.

When capture fails (end of file, camera unplugged) the reader stops; ``read`` returns the
frames still queued, then raises :class:`CameraDisconnectedError`.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from beadsight.devices.base import (
    CameraConfigError,
    CameraDisconnectedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Frame,
    host_now,
)

logger = logging.getLogger(__name__)

DEFAULT_WIDTH_PX = 1280  # the reference sensor camera, MJPG
DEFAULT_HEIGHT_PX = 1024
DEFAULT_FPS = 30.0
DEFAULT_QUEUE_FRAMES = 64  # ~2 s at 30 fps; read() must keep up on average
GAP_FACTOR = 1.5  # a capture gap above this many frame periods means frames were lost
FPS_TOLERANCE = 0.05  # relative fps mismatch accepted when verifying the device
MIN_READ_TIMEOUT_S = 2.0  # default read timeout: max(this, 10 frame periods)


@dataclass(frozen=True)
class CameraStats:
    """Frame counters since connect (see the module docstring)."""

    captured: int
    delivered: int
    dropped: int
    overflowed: int
    skipped: int


def verify_mode(
    name: str, requested: tuple[int | None, int | None], actual: tuple[int, int], hint: str
) -> None:
    """Raise CameraConfigError naming the camera and both resolutions if they differ.

    requested: (width, height) px, None = accept any; actual: what the device delivers.
    """
    req_w, req_h = requested
    if (req_w is not None and req_w != actual[0]) or (req_h is not None and req_h != actual[1]):
        want = f"{req_w or '*'}x{req_h or '*'}"
        raise CameraConfigError(
            name, f"delivers {actual[0]}x{actual[1]} frames but {want} was requested", hint
        )


class BufferedCamera:
    """Base class: background capture, ordered queue, newest frame, drop accounting.

    Subclasses implement ``_open() -> (width, height, fps)``, ``_grab() -> image or None``
    (None: the stream ended; set ``self._end_reason``) and ``_release()``.

    live: True for devices (count timestamp gaps, drop the oldest frame when the queue is
    full); False for files (no gap accounting, the reader waits when the queue is full).
    """

    def __init__(self, name: str, *, queue_frames: int = DEFAULT_QUEUE_FRAMES, live: bool = True):
        if queue_frames < 1:
            raise ValueError(f"queue_frames must be >= 1, got {queue_frames}")
        self.name = name
        self.live = live
        self.width = 0
        self.height = 0
        self.fps = DEFAULT_FPS
        self._queue: deque[Frame] = deque()
        self._queue_frames = int(queue_frames)
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._returned_index = -1  # newest index handed out by read / read_latest
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._ended = False
        self._end_reason = "stopped delivering frames"
        self._captured = self._delivered = self._dropped = self._overflowed = self._skipped = 0
        self._last_capture_mono: float | None = None

    # --- subclass hooks -----------------------------------------------------------------
    def _open(self) -> tuple[int, int, float]:
        raise NotImplementedError

    def _grab(self) -> np.ndarray | None:
        raise NotImplementedError

    def _release(self) -> None:
        pass

    # --- lifecycle --------------------------------------------------------------------
    def connect(self) -> None:
        """Open and verify the source, then start the reader thread."""
        if self._thread is not None:
            return
        self.width, self.height, self.fps = self._open()
        with self._cond:  # a reconnect starts a fresh stream; indices keep counting up
            self._queue.clear()
            self._latest = None
            self._last_capture_mono = None
        self._stop.clear()
        self._ended = False
        self._thread = threading.Thread(target=self._run, name=f"{self.name} reader", daemon=True)
        self._thread.start()
        logger.info("%s: %dx%d at %.3g fps", self.name, self.width, self.height, self.fps)

    def close(self) -> None:
        """Stop the reader and release the device. Safe to call twice."""
        self._stop.set()
        with self._cond:
            if not self._ended:
                self._end_reason = "was closed"
            self._cond.notify_all()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        self._release()

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def stats(self) -> CameraStats:
        with self._cond:
            return CameraStats(
                self._captured, self._delivered, self._dropped, self._overflowed, self._skipped
            )

    @property
    def ended(self) -> bool:
        """True once the reader stopped (end of file, unplugged) - frames may still be queued."""
        return self._ended

    # --- reading ----------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> Frame:
        """The next frame in capture order (waits up to ``timeout_s``).

        Raises CameraDisconnectedError once the stream ended and the queue is empty,
        DeviceTimeoutError when no frame arrives in time.
        """
        deadline = time.monotonic() + self._timeout(timeout_s)
        with self._cond:
            while not self._queue:
                self._wait(deadline, timeout_s)
            frame = self._queue.popleft()
            self._returned_index = frame.index
            self._delivered += 1
            self._cond.notify_all()
            return frame

    def read_latest(self, timeout_s: float | None = None) -> Frame:
        """The newest frame, never one returned before: waits for a new one if needed.

        Older queued frames are discarded (counted as ``skipped``). Raises like :meth:`read`.
        """
        deadline = time.monotonic() + self._timeout(timeout_s)
        with self._cond:
            while self._latest is None or self._latest.index <= self._returned_index:
                self._wait(deadline, timeout_s)
            frame = self._latest
            self._skipped += sum(1 for f in self._queue if f.index < frame.index)
            self._queue.clear()
            self._returned_index = frame.index
            self._delivered += 1
            self._cond.notify_all()
            return frame

    def _timeout(self, timeout_s: float | None) -> float:
        if timeout_s is not None:
            return float(timeout_s)
        return max(MIN_READ_TIMEOUT_S, 10.0 / self.fps if self.fps > 0 else MIN_READ_TIMEOUT_S)

    def _wait(self, deadline: float, timeout_s: float | None) -> None:
        """Wait on the condition (held) for news; raise if the stream is over or too late."""
        if self._ended:
            raise CameraDisconnectedError(
                self.name,
                f"{self._end_reason} after {self._captured} frames",
                self._disconnect_hint(),
            )
        if self._thread is None:
            raise DeviceNotConnectedError(
                self.name, "not connected", "call connect() or use 'with'"
            )
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceTimeoutError(
                self.name,
                f"no new frame within {self._timeout(timeout_s):g} s (expected {self.fps:g} fps)",
                "is the camera still plugged in and lit?",
            )
        self._cond.wait(remaining)

    def _disconnect_hint(self) -> str | None:
        return None

    # --- reader thread ------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                image = self._grab()
                t_unix, t_mono = host_now()
                if image is None:
                    break
                self._push(image, t_unix, t_mono)
        except Exception as e:  # noqa: BLE001 - a backend failure ends the stream, with its reason
            logger.exception("%s: capture failed", self.name)
            self._end_reason = f"capture failed ({e})"
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()
            if not self._stop.is_set():
                logger.warning(
                    "%s: %s after %d frames", self.name, self._end_reason, self._captured
                )

    def _push(self, image: np.ndarray, t_unix: float, t_mono: float) -> None:
        with self._cond:
            if self.live:
                self._count_gap(t_mono)
            else:
                while len(self._queue) >= self._queue_frames and not self._stop.is_set():
                    self._cond.wait(0.1)
            frame = Frame(image=image, index=self._captured, t_mono=t_mono, t_unix=t_unix)
            self._captured += 1
            if len(self._queue) >= self._queue_frames:
                self._queue.popleft()
                self._overflowed += 1
            self._queue.append(frame)
            self._latest = frame
            self._cond.notify_all()

    def _count_gap(self, t_mono: float) -> None:
        last, self._last_capture_mono = self._last_capture_mono, t_mono
        if last is None or self.fps <= 0:
            return
        gap_s = t_mono - last
        if gap_s > GAP_FACTOR / self.fps:
            lost = max(1, round(gap_s * self.fps) - 1)
            self._dropped += lost
            logger.warning(
                "%s: %.0f ms capture gap, ~%d frame(s) dropped", self.name, gap_s * 1e3, lost
            )


class OpenCVCamera(BufferedCamera):
    """A camera (index, e.g. 0 for /dev/video0) or a video file, read with OpenCV.

    width, height: requested frame size in px; verified against the frames actually
    delivered (CameraConfigError names both); None accepts whatever comes (handy for
    files). fps: requested rate for devices (verified from the driver's report); files
    play at their own fps. fourcc: pixel format asked of devices ("MJPG" is needed for
    1280x1024 at 30 fps over USB 2). realtime: files only; True paces frames at the file's
    fps like a live camera, False reads as fast as the consumer takes them.
    """

    def __init__(
        self,
        source: int | str,
        width: int | None = DEFAULT_WIDTH_PX,
        height: int | None = DEFAULT_HEIGHT_PX,
        fps: float = DEFAULT_FPS,
        fourcc: str = "MJPG",
        *,
        realtime: bool = True,
        queue_frames: int = DEFAULT_QUEUE_FRAMES,
        backend: int | None = None,
        name: str | None = None,
    ):
        if isinstance(source, str) and source.strip().isdigit():
            source = int(source)
        self.source = source
        self.is_file = isinstance(source, str)
        if len(fourcc) != 4:
            raise ValueError(f"fourcc must be 4 characters, got {fourcc!r}")
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        default_name = f"camera {os.path.basename(source)}" if self.is_file else f"camera {source}"
        super().__init__(name or default_name, queue_frames=queue_frames, live=not self.is_file)
        self.requested = (width, height)
        self.requested_fps = float(fps)
        self.fourcc = fourcc
        self.realtime = realtime
        self.backend = backend
        self._cap = None
        self._first: np.ndarray | None = None
        self._t_start: float | None = None
        self._file_index = 0

    def _open(self) -> tuple[int, int, float]:
        import cv2

        if self.is_file and not os.path.isfile(self.source):  # type: ignore[arg-type]
            raise DeviceNotConnectedError(self.name, f"video file {self.source} does not exist")
        cap = (
            cv2.VideoCapture(self.source)
            if self.backend is None
            else cv2.VideoCapture(self.source, self.backend)
        )
        if not cap.isOpened():
            cap.release()
            raise DeviceNotConnectedError(self.name, "could not be opened", self._disconnect_hint())
        self._cap = cap
        try:
            if not self.is_file:
                self._configure(cap, cv2)
            ok, first = cap.read()
            if not ok or first is None:
                raise DeviceNotConnectedError(
                    self.name, "opened but delivered no frame", self._disconnect_hint()
                )
            height, width = first.shape[:2]
            verify_mode(self.name, self.requested, (width, height), self._mode_hint())
            fps = self._verified_fps(cap, cv2)
        except BaseException:
            self._release()
            raise
        self._first = first
        self._file_index = 0
        self._t_start = None
        return width, height, fps

    def _configure(self, cap, cv2) -> None:
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.fourcc))
        width, height = self.requested
        if width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        cap.set(cv2.CAP_PROP_FPS, self.requested_fps)
        reported = int(cap.get(cv2.CAP_PROP_FOURCC))
        got = "".join(chr((reported >> (8 * i)) & 0xFF) for i in range(4))
        if reported and got != self.fourcc:
            logger.warning(
                "%s: asked for %s pixels, driver reports %r", self.name, self.fourcc, got
            )

    def _verified_fps(self, cap, cv2) -> float:
        reported = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if self.is_file:
            if not reported > 0 or not math.isfinite(reported):
                logger.warning(
                    "%s: the file reports no fps; assuming %g", self.name, self.requested_fps
                )
                return self.requested_fps
            return reported
        if reported > 0 and abs(reported - self.requested_fps) > FPS_TOLERANCE * self.requested_fps:
            raise CameraConfigError(
                self.name,
                f"runs at {reported:g} fps but {self.requested_fps:g} fps was requested "
                f"(at {self.requested[0]}x{self.requested[1]} {self.fourcc})",
                self._mode_hint(),
            )
        return reported if reported > 0 else self.requested_fps

    def _grab(self) -> np.ndarray | None:
        if self._first is not None:  # the frame read while verifying the mode
            image, self._first = self._first, None
        else:
            ok, image = self._cap.read() if self._cap is not None else (False, None)
            if not ok or image is None:
                self._end_reason = (
                    "end of file" if self.is_file else "stopped delivering frames (unplugged?)"
                )
                return None
        if self.is_file and self.realtime:
            self._pace()
        self._file_index += 1
        return image

    def _pace(self) -> None:
        """Hold a file frame until its time at the file's fps (like a live camera)."""
        if self._t_start is None:
            self._t_start = time.monotonic()
        due = self._t_start + self._file_index / self.fps
        delay = due - time.monotonic()
        if delay > 0:
            self._stop.wait(delay)

    def _release(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _mode_hint(self) -> str:
        if self.is_file:
            return "pass width=None, height=None to accept the file's size"
        return (
            f"list the supported modes with: v4l2-ctl -d /dev/video{self.source} --list-formats-ext"
        )

    def _disconnect_hint(self) -> str | None:
        if self.is_file:
            return None
        return "is it plugged in? ls /dev/video*; is another program (cheese, OBS, another beadsight) using it?"
