"""The data-collection rig's devices: printer, scale, camera, and their virtual twins.

Drivers (each a context manager with ``connect()`` / ``close()``):

* :class:`MarlinPrinter` - G-code over serial with line numbers, checksums, resends and
  a :class:`SafetyEnvelope` checked before anything is sent.
* :class:`HX711Scale` - background reader of the Arduino scale (beadsight firmware or the
  reference sketch), host-timestamped :class:`ScaleReading` objects.
* :class:`OpenCVCamera` - camera index, device path or video file; like every
  :class:`Camera`, a background reader of timestamped :class:`Frame` objects with
  ``read`` / ``async_read`` / ``read_latest`` (:mod:`beadsight.devices.camera`).

Virtual twins live in :mod:`beadsight.devices.virtual` (``VirtualPrinter``,
``VirtualScale``, ``VirtualCamera``, ``PlaybackCamera``, ``SimCamera``, ``VirtualRig``);
they are importable from here too, lazily. Errors are :class:`DeviceError` subclasses
naming the device, with a hint.
"""

from beadsight.devices.base import (
    Camera,
    CameraConfigError,
    CameraDisconnectedError,
    CameraEndedError,
    CommandRecord,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Frame,
    Printer,
    PrinterDesyncError,
    PrinterError,
    SafetyError,
    Scale,
    ScaleError,
    ScaleReading,
    VideoFileNotFoundError,
)
from beadsight.devices.camera import BufferedCamera, CameraStats
from beadsight.devices.envelope import SafetyEnvelope
from beadsight.devices.hx711 import HX711Scale, ScaleStats
from beadsight.devices.marlin import MarlinPrinter
from beadsight.devices.opencv import OpenCVCamera

_VIRTUAL = (
    "PlaybackCamera",
    "SimCamera",
    "SimClock",
    "VirtualCamera",
    "VirtualPrinter",
    "VirtualRig",
    "VirtualScale",
)

__all__ = [
    "BufferedCamera",
    "Camera",
    "CameraConfigError",
    "CameraDisconnectedError",
    "CameraEndedError",
    "CameraStats",
    "CommandRecord",
    "DeviceError",
    "DeviceNotConnectedError",
    "DeviceTimeoutError",
    "Frame",
    "HX711Scale",
    "MarlinPrinter",
    "OpenCVCamera",
    "Printer",
    "PrinterDesyncError",
    "PrinterError",
    "SafetyEnvelope",
    "SafetyError",
    "Scale",
    "ScaleError",
    "ScaleReading",
    "ScaleStats",
    "VideoFileNotFoundError",
    *_VIRTUAL,
]


def __getattr__(name: str):
    if name in _VIRTUAL:  # the virtual twins need pty (POSIX) and, for the rig, the simulator
        from beadsight.devices import virtual

        return getattr(virtual, name)
    raise AttributeError(f"module 'beadsight.devices' has no attribute {name!r}")
