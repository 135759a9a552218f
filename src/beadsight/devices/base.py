"""Small device interfaces (Camera, Printer, Scale), their records and their exceptions.

Collection and live sensing take device objects typed by these protocols, so they run
unchanged on the real drivers (:class:`~beadsight.devices.marlin.MarlinPrinter`,
:class:`~beadsight.devices.hx711.HX711Scale`,
:class:`~beadsight.devices.opencv.OpenCVCamera`) and on the virtual twins
(:mod:`beadsight.devices.virtual`: the rig, the simulated sensor camera).

Timestamps: every record carries two host clocks read at the same moment:
``t_unix`` (``time.time()``, float64 s since the epoch, comparable across machines and
with the reference logs) and ``t_mono`` (``time.monotonic()``, float64 s, never jumps;
use it to align streams inside one session).

Every exception is a :class:`DeviceError` (a :class:`beadsight.errors.BeadSightError`,
so the CLI prints it as one line); its message starts with the device's name (e.g.
``"printer /dev/ttyUSB0"``) and ends with a hint when there is a likely fix.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

from beadsight.errors import BeadSightError


# --- exceptions ----------------------------------------------------------------------
class DeviceError(BeadSightError):
    """A device failed or refused; ``device`` names it, ``hint`` suggests a fix (or None)."""

    def __init__(self, device: str, message: str, hint: str | None = None):
        self.device = device
        self.detail = message
        self.hint = hint
        text = f"{device}: {message}"
        if hint:
            text += f" (hint: {hint})"
        super().__init__(text)

    def __reduce__(self):  # keep the three-argument constructor picklable
        return (type(self), (self.device, self.detail, self.hint))


class DeviceNotConnectedError(DeviceError):
    """The device is absent, busy, unplugged, or was never connected."""


class DeviceTimeoutError(DeviceError):
    """The device did not answer (or stopped streaming) within the allowed time."""


def wait_or_time_out(
    cond: threading.Condition, deadline: float, device: str, message: str, hint: str | None = None
) -> None:
    """Wait on ``cond`` (held by the caller) for news until ``deadline`` (``time.monotonic``);
    once it has passed, raise :class:`DeviceTimeoutError` (``device``, ``message``, ``hint``)."""
    remaining = deadline - time.monotonic()
    if remaining <= 0:
        raise DeviceTimeoutError(device, message, hint)
    cond.wait(remaining)


class SafetyError(DeviceError):
    """A command was refused before anything was sent, because it could damage the rig."""


class PrinterError(DeviceError):
    """The printer reported an error (``Error:...``) or is halted."""


class PrinterDesyncError(PrinterError):
    """Printer and host disagree about which commands ran (e.g. the printer asked again for
    a line it had already acknowledged, or reports another position than commanded).
    Nothing was replayed; the driver raised the finger where it could. Home again."""


class ScaleError(DeviceError):
    """The scale rejected a command (``ERR ...``) or gave unusable data."""


class CameraConfigError(DeviceError):
    """The camera does not deliver the requested resolution / frame rate."""


class CameraDisconnectedError(DeviceNotConnectedError):
    """The camera stopped delivering frames (end of file, unplugged) and the buffer is empty."""


class CameraEndedError(CameraDisconnectedError):
    """A finite camera (a video file, played frames) delivered its last frame: not a fault."""


class VideoFileNotFoundError(DeviceNotConnectedError, FileNotFoundError):
    """The video file a camera should play does not exist (also a FileNotFoundError)."""


# --- clocks and records ------------------------------------------------------------------
def host_now() -> tuple[float, float]:
    """``(t_unix, t_mono)``: both host clocks read back to back, float64 seconds."""
    return time.time(), time.monotonic()


class CommandRecord(NamedTuple):
    """One G-code command the printer acknowledged (``ok``); unpacks as a 6-tuple.

    ``t_unix`` / ``t_mono``: host time the ``ok`` arrived (s). For ``G1`` the printer
    acknowledges after *planning*, so motion ends later; the ``M400`` record that
    follows marks arrival. ``x_mm, y_mm, z_mm``: the commanded printer position after
    the command (absolute, mm; NaN while unknown, i.e. before homing).
    """

    t_unix: float
    t_mono: float
    gcode: str
    x_mm: float
    y_mm: float
    z_mm: float


@dataclass(frozen=True)
class ScaleReading:
    """One scale reading.

    ``t_unix`` / ``t_mono``: host time the line arrived (s). ``grams``: load in grams
    (2 decimals from the device, after any host-side tare/gain). ``force_n``: the same
    load in newtons (``grams * 9.81e-3``, the reference factor). ``seq``: sample number
    (from the device for the beadsight firmware, reconstructed for the reference sketch;
    gaps mean dropped readings). ``device_ms``: the Arduino's ``millis()`` when sampled,
    or None when the protocol does not send it.
    """

    t_unix: float
    t_mono: float
    grams: float
    force_n: float
    seq: int
    device_ms: int | None


@dataclass(frozen=True)
class Frame:
    """One captured camera frame (every camera, for collection and live sensing alike).

    ``image``: (H, W, 3) uint8 in ``channel_order`` ("BGR", OpenCV's order, for cameras and
    video files; "RGB" for the simulated sensor). ``index``: capture order since the camera
    object was made, counting on across reconnects and loops of a file; a jump between two
    frames you read means frames were skipped or dropped in between. ``t_mono`` /
    ``t_unix``: when the frame was captured (s), in host time (or on a virtual camera's
    ``SteppedClock`` / ``FrameClock``); ``t_unix`` strictly increases from frame to frame. ``reference_force_n``: the true force on the sensor when the camera
    knows it (the simulator), else NaN. ``file_index``: the frame's row in the file the
    camera plays (a replayed dataset, :class:`~beadsight.devices.replay.DatasetCamera`),
    None for cameras that do not play one; unlike ``index`` it starts again on a loop.
    """

    image: np.ndarray
    index: int
    t_mono: float
    t_unix: float
    channel_order: str = "BGR"
    reference_force_n: float = math.nan
    file_index: int | None = None

    @property
    def source_index(self) -> int:
        """Where the frame sits in its source: ``file_index`` when the camera plays a
        file, else ``index`` (what readings files record as ``frame_index``)."""
        return self.index if self.file_index is None else self.file_index

    @property
    def timestamp_s(self) -> float:
        """The capture time on the unix clock (``t_unix``): the stamp readings carry."""
        return self.t_unix


# --- protocols --------------------------------------------------------------------------
@runtime_checkable
class Printer(Protocol):
    """A motion stage carrying the finger (Marlin printer or its virtual twin)."""

    name: str

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def home(self) -> tuple[float, float, float]: ...
    def move(
        self, x: float | None, y: float | None, z: float | None, feed_mm_min: float
    ) -> None: ...
    def dwell(self, ms: float) -> None: ...
    def wait_for_motion(self) -> None: ...
    def position(self) -> tuple[float, float, float]: ...
    def heaters_off(self) -> None: ...
    def emergency_stop(self) -> None: ...


@runtime_checkable
class Scale(Protocol):
    """A force sensor streaming timestamped readings (HX711 scale or its virtual twin)."""

    name: str

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def latest(self) -> ScaleReading | None: ...
    def readings_since(self, t_mono: float) -> list[ScaleReading]: ...
    def drain(self) -> list[ScaleReading]: ...
    def tare(self) -> None: ...
    def calibrate(self, known_grams: float) -> float: ...


@runtime_checkable
class Camera(Protocol):
    """A camera with a background reader: USB camera, video file, simulated sensor, virtual rig.

    The implementations are :class:`~beadsight.devices.opencv.OpenCVCamera` (camera index,
    device path or video file), :class:`~beadsight.devices.virtual.VirtualCamera` (the
    virtual rig), :class:`~beadsight.devices.virtual.PlaybackCamera` and
    :class:`~beadsight.devices.virtual.SimCamera` (the simulated sensor). ``width``,
    ``height`` (px) and ``fps`` (frames per host second) are known once connected.

    Three ways to read, as in lerobot's cameras; none ever hands out a frame twice:

    * :meth:`read` - the next frame in capture order (every frame: recording);
    * :meth:`async_read` - every frame the background reader captured since the last
      read, oldest first, at most ``max_frames`` of the newest (the older ones count as
      skipped), waiting for one if none is new (live sensing keeps its window whole);
    * :meth:`read_latest` - only the newest frame, waiting for one if it was handed out
      already (control loops; lerobot's ``async_read``).

    Each waits up to ``timeout_s`` (None: the camera's default) and raises
    :class:`DeviceTimeoutError` when nothing new came, :class:`CameraEndedError` once a
    finite camera played its last frame, :class:`CameraDisconnectedError` once a live one
    stopped, and :class:`DeviceNotConnectedError` before :meth:`connect`. Errors name the
    camera and, where there is a likely fix, give a hint.
    """

    name: str
    width: int
    height: int
    fps: float

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def read(self, timeout_s: float | None = None) -> Frame: ...
    def async_read(
        self, timeout_s: float | None = None, max_frames: int | None = None
    ) -> list[Frame]: ...
    def read_latest(self, timeout_s: float | None = None) -> Frame: ...
    def __enter__(self) -> Camera: ...
    def __exit__(self, *exc: object) -> None: ...


class DeviceContext:
    """Mixin: ``with device:`` connects on entry and closes on exit (every device has
    ``connect()`` and an idempotent ``close()``)."""

    def connect(self) -> None:  # pragma: no cover - every device defines its own
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - every device defines its own
        raise NotImplementedError

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
