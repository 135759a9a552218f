"""USB cameras and video files, read with OpenCV: :class:`OpenCVCamera`.

One class for the three ways a frame source is named: a camera index (``0`` for
/dev/video0), a device path (``/dev/video2``) and a video file path. Cameras are asked
for a mode (size, rate, pixel format) and refuse to start when the driver delivers
another; files play at their own fps (``realtime``) or as fast as they are read, and
can ``loop``. Both are :class:`~beadsight.devices.camera.BufferedCamera` objects, so
they share the reader thread, the reads and the frame accounting with the virtual ones.
"""

from __future__ import annotations

import logging
import math
import os
import stat

import numpy as np

from beadsight.devices.base import (
    CameraConfigError,
    DeviceNotConnectedError,
    VideoFileNotFoundError,
)
from beadsight.devices.camera import (
    DEFAULT_FPS,
    DEFAULT_HEIGHT_PX,
    DEFAULT_QUEUE_FRAMES,
    DEFAULT_WIDTH_PX,
    BufferedCamera,
    Captured,
)

logger = logging.getLogger(__name__)

FPS_TOLERANCE = 0.05  # relative fps mismatch accepted when verifying the device


def is_device_path(source: str) -> bool:
    """True for a camera device node (``/dev/video0``), False for a (video) file path."""
    if source.startswith("/dev/"):
        return True
    try:
        return stat.S_ISCHR(os.stat(source).st_mode)
    except OSError:
        return False


class OpenCVCamera(BufferedCamera):
    """A camera (index, e.g. 0 for /dev/video0, or device path) or a video file.

    width, height: requested frame size in px; verified against the frames actually
    delivered (CameraConfigError names both); None accepts whatever comes (handy for
    files). fps: requested rate for cameras (verified from the driver's report); files
    play at their own fps. fourcc: pixel format asked of cameras ("MJPG" is needed for
    1280x1024 at 30 fps over USB 2). realtime: files only; True paces frames at the
    file's fps like a live camera, False reads as fast as the consumer takes them.
    loop: files only; start again at the end (indices keep counting up).
    """

    def __init__(
        self,
        source: int | str | os.PathLike,
        width: int | None = DEFAULT_WIDTH_PX,
        height: int | None = DEFAULT_HEIGHT_PX,
        fps: float = DEFAULT_FPS,
        fourcc: str = "MJPG",
        *,
        realtime: bool = True,
        loop: bool = False,
        queue_frames: int = DEFAULT_QUEUE_FRAMES,
        backend: int | None = None,
        name: str | None = None,
    ):
        if isinstance(source, os.PathLike):
            source = os.fspath(source)
        if isinstance(source, str) and source.strip().isdigit():
            source = int(source)
        if len(fourcc) != 4:
            raise ValueError(f"fourcc must be 4 characters, got {fourcc!r}")
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.source = source
        self.is_file = isinstance(source, str) and not is_device_path(source)
        default_name = f"camera {os.path.basename(source)}" if self.is_file else f"camera {source}"
        super().__init__(
            name or default_name,
            (width, height),
            queue_frames=queue_frames,
            live=not self.is_file,
            paced=self.is_file and realtime,
        )
        self.requested_fps = float(fps)
        self.fourcc = fourcc
        self.realtime = realtime
        self.loop = loop and self.is_file
        self.backend = backend
        self._cap = None

    def _open(self) -> float:
        import cv2

        if self.is_file and not os.path.isfile(self.source):  # type: ignore[arg-type]
            raise VideoFileNotFoundError(self.name, f"video file {self.source} does not exist")
        cap = self._capture(cv2)
        if not cap.isOpened():
            cap.release()
            raise DeviceNotConnectedError(self.name, "could not be opened", self._disconnect_hint())
        self._cap = cap
        try:
            if not self.is_file:
                self._configure(cap, cv2)
            return self._verified_fps(cap, cv2)
        except BaseException:
            self._release()
            raise

    def _capture(self, cv2):
        if self.backend is None:
            return cv2.VideoCapture(self.source)
        return cv2.VideoCapture(self.source, self.backend)

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

    def _grab(self) -> Captured | None:
        image = self._read_image()
        if image is None and self.loop and self._captured > 0:
            logger.info("%s: end of file, looping", self.name)
            self._rewind()
            image = self._read_image()
        if image is None:
            if self.is_file:
                return self._end("end of file", finite=True)
            return self._end("stopped delivering frames (unplugged?)")
        return image, math.nan

    def _read_image(self) -> np.ndarray | None:
        ok, image = self._cap.read() if self._cap is not None else (False, None)
        return image if ok and image is not None else None

    def _rewind(self) -> None:
        """Reopen the file at its first frame (seeking is not reliable in every container)."""
        import cv2

        self._release()
        self._cap = self._capture(cv2)

    def _release(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _mode_hint(self) -> str:
        if self.is_file:
            return "pass width=None, height=None to accept the file's size"
        device = self.source if isinstance(self.source, str) else f"/dev/video{self.source}"
        return f"list the supported modes with: v4l2-ctl -d {device} --list-formats-ext"

    def _disconnect_hint(self) -> str | None:
        if self.is_file:
            return None
        return "is it plugged in? ls /dev/video*; is another program (cheese, OBS, another beadsight) using it?"
