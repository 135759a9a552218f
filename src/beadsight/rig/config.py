"""Settings of a collection session besides its press plan: the devices to open
(:class:`DeviceSpec`), the simulated rig (:class:`VirtualRigSpec`) and the safety
defaults of :func:`beadsight.rig.collect.collect`. Imports nothing heavy, so the command
line reads its defaults here."""

from __future__ import annotations

from dataclasses import dataclass

from beadsight.errors import ConfigError

FORCE_LIMIT_N = 40.0  # a press is aborted (finger lifted) above this force, newtons
ON_FORCE_LIMIT = ("stop", "skip")  # after an aborted press: stop the session, or go on
SCALE_TIMEOUT_S = 2.0  # the force check needs a scale reading at most this old, seconds
SCALE_PROTOCOLS = ("auto", "beadsight", "reference")  # our firmware, the reference sketch
CAMERA_MODES = ("raw", "sensor")  # the virtual camera: 1280x1024 fisheye, or sensor space


def _positive(owner: object, *names: str) -> None:
    for name in names:
        value = getattr(owner, name)
        if value is not None and not value > 0:
            raise ConfigError(f"{name} must be > 0, got {value!r}")


@dataclass(frozen=True)
class DeviceSpec:
    """Which devices to open: serial ports and a camera source (index or video file)."""

    printer_port: str
    scale_port: str
    camera: int | str
    printer_baud: int = 115200  # Marlin over USB
    scale_baud: int = 57600  # the HX711 sketch
    scale_protocol: str = "auto"  # "auto", "beadsight" (our firmware) or "reference"
    camera_width: int | None = 1280
    camera_height: int | None = 1024
    camera_fps: float = 30.0

    def __post_init__(self) -> None:
        _positive(self, "printer_baud", "scale_baud", "camera_width", "camera_height", "camera_fps")
        if self.scale_protocol not in SCALE_PROTOCOLS:
            raise ConfigError(
                f"scale_protocol must be one of {SCALE_PROTOCOLS}, got {self.scale_protocol!r}"
            )


@dataclass(frozen=True)
class VirtualRigSpec:
    """The simulated rig for ``beadsight collect --virtual``."""

    time_scale: float = 1.0  # simulated seconds per host second
    camera_mode: str = "raw"  # "raw" (1280x1024 fisheye, slow to render) or "sensor"
    image_size_px: int = 256  # sensor-space frame size ("sensor" mode)
    camera_fps: float | None = None  # default: the simulator's (30)
    seed: int = 0  # the simulated pouch
    scale_protocol: str = "beadsight"

    def __post_init__(self) -> None:
        _positive(self, "time_scale", "image_size_px", "camera_fps")
        if self.camera_mode not in CAMERA_MODES:
            raise ConfigError(
                f"camera_mode must be one of {CAMERA_MODES}, got {self.camera_mode!r}"
            )
