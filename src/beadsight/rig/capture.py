"""The collection's capture thread: every camera frame and scale reading into the raw recording.

A :class:`CaptureRecorder` runs on its own thread (a :class:`~beadsight.devices.reader.ReaderThread`)
while the main thread drives the printer: it takes each frame in capture order with
:meth:`~beadsight.devices.Camera.read` (never skipping one) and drains the scale between
frames. It never raises: the first failure is kept in :attr:`CaptureRecorder.failure` as
``(status, message)`` for the session to stop on.
"""

from __future__ import annotations

import logging
import threading

from beadsight.data.recording import RecordingError, RecordingWriter
from beadsight.devices.base import (
    Camera,
    CameraDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
    Scale,
)
from beadsight.devices.reader import ReaderThread

logger = logging.getLogger(__name__)

CAMERA_READ_TIMEOUT_S = 0.5  # wait this long for a frame, then check for stop
RECORDER_JOIN_S = 5.0  # stop(): how long to wait for the thread


class CaptureRecorder:
    """Background thread: every camera frame and scale reading into ``writer``."""

    def __init__(self, writer: RecordingWriter, camera: Camera, scale: Scale):
        self.writer = writer
        self.camera = camera
        self.scale = scale
        self.failure: tuple[str, str] | None = None
        self.timeouts = 0  # camera reads that found no frame in time
        self._reader = ReaderThread("beadsight recorder", self._run)

    def start(self) -> None:
        self._reader.start()

    def stop(self) -> None:
        """Stop recording (the scale's last readings are written as the thread ends)."""
        self._reader.stop(RECORDER_JOIN_S)

    def _fail(self, status: str, message: str) -> None:
        if self.failure is None:
            self.failure = (status, message)
            logger.error("%s", message)

    def _run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                self._drain_scale()
                self._record_frame()
            except CameraDisconnectedError as e:
                self._fail("camera_disconnected", f"camera disconnected: {e}")
                break
            except RecordingError as e:
                self._fail("write_error", str(e))
                break
            except DeviceError as e:
                self._fail("scale_error", f"scale failed: {e}")
                break
            except Exception as e:  # noqa: BLE001 - the main thread reports it
                logger.exception("recorder thread crashed")
                self._fail("write_error", f"recorder failed: {type(e).__name__}: {e}")
                break
        try:
            self._drain_scale()
        except (DeviceError, RecordingError):
            pass

    def _record_frame(self) -> None:
        try:
            frame = self.camera.read(timeout_s=CAMERA_READ_TIMEOUT_S)
        except DeviceTimeoutError:
            self.timeouts += 1
            return
        self.writer.write_frame(
            frame.image, t_unix=frame.t_unix, t_mono=frame.t_mono, camera_index=frame.index
        )

    def _drain_scale(self) -> None:
        readings = self.scale.drain()
        if readings:
            self.writer.write_readings(readings)
