"""Configuration: frozen dataclasses with units in field names.

Defaults are the published BeadSight system (see docs/data-format.md). Every
dataclass validates itself in ``__post_init__`` and round-trips through plain
dicts (``to_dict`` / ``from_dict``) so it can be stored in checkpoints, HDF5
attributes and run folders as JSON.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, TypeVar

from beadsight.errors import ConfigError  # defined there; importable from here as before

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# --- physical constants and units -------------------------------------------------
STANDARD_GRAVITY_M_S2 = 9.80665  # m/s^2; 1 g-force = 9.80665e-3 N
REFERENCE_G_TO_N = 9.81e-3  # the reference code converts grams with g = 9.81 m/s^2
DEFAULT_SPLIT_FRACTIONS = (0.7, 0.1, 0.2)  # train, val, test fractions of presses (paper)
REFERENCE_CENTRE_XY_MM = (151.8, 108.9)  # printer XY of the sensor centre (reference rig)
DEVICE_CHOICES = "auto, cpu, cuda, cuda:N or mps"  # torch devices (beadsight.torch_device)

T = TypeVar("T")


class _Serializable:
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[arg-type]

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
        """Build from a dict, ignoring unknown keys; list values become tuples."""
        names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        kwargs = {}
        for key, value in data.items():
            if key in names:
                kwargs[key] = tuple(value) if isinstance(value, list) else value
        return cls(**kwargs)


@dataclass(frozen=True)
class SensorGeometry(_Serializable):
    """Where the sensor's image sits in the world.

    The image spans ``sensor_size_mm`` in both axes. Positions are millimetres
    from the sensor centre in the printer frame: printer +X maps to image -column,
    printer +Y to image -row (reference convention).
    """

    sensor_size_mm: float = 41.0  # side of the square field of view
    image_size_px: int = 256  # side of the square sensor-space image
    finger_radius_mm: float = 6.25  # flat cylindrical finger, 12.5 mm diameter
    press_range_mm: float = 13.75  # presses lie within +-this of the centre in X and Y

    def __post_init__(self) -> None:
        if not self.sensor_size_mm > 0:
            raise ConfigError(f"sensor_size_mm must be > 0, got {self.sensor_size_mm}")
        if int(self.image_size_px) != self.image_size_px or self.image_size_px < 8:
            raise ConfigError(f"image_size_px must be an integer >= 8, got {self.image_size_px}")
        if not 0 < self.finger_radius_mm < self.sensor_size_mm / 2:
            raise ConfigError(
                f"finger_radius_mm must be in (0, sensor_size_mm/2), got {self.finger_radius_mm}"
            )
        object.__setattr__(self, "image_size_px", int(self.image_size_px))

    @property
    def mm_per_px(self) -> float:
        return self.sensor_size_mm / self.image_size_px

    @property
    def pixel_area_m2(self) -> float:
        return (self.mm_per_px * 1e-3) ** 2

    def with_image_size(self, image_size_px: int) -> SensorGeometry:
        return dataclasses.replace(self, image_size_px=image_size_px)


@dataclass(frozen=True)
class ContactThresholds(_Serializable):
    """Force hysteresis that separates presses (reference: 50 g in, 10 g out)."""

    contact_n: float = 50 * REFERENCE_G_TO_N  # at or above: contact begins
    release_n: float = 10 * REFERENCE_G_TO_N  # at or below: contact ends

    def __post_init__(self) -> None:
        if not self.release_n < self.contact_n:
            raise ConfigError(
                f"release_n ({self.release_n}) must be below contact_n ({self.contact_n})"
            )


@dataclass(frozen=True)
class ModelConfig(_Serializable):
    """The reference U-Net's hyper-parameters.

    Two counts of frames, never confused: ``frames`` (T) is how many frames the
    network sees, stacked on the channel axis; :attr:`span` is how many consecutive
    camera frames one input covers, ``(frames - 1) * frame_stride + 1``.
    """

    frames: int = 15  # T: frames stacked on the channel axis, oldest first
    frame_stride: int = 1  # the stacked frames are this many frames apart (1: consecutive)
    width: int = 16  # channels of the first encoder block; doubled at each level
    up_kernel: int = 1  # 1 = reference weights, 3 = the paper's text
    dropout: float = 0.2  # in every conv block but the last decoder block
    rest_input: bool = (
        False  # rest-referenced: the network also sees the pouch at rest (+3 channels)
    )
    # rest-referenced, contrast-normalised: the rest image standardised per channel, and each
    # seen frame's change from rest divided by the rest's per-channel contrast (its std)
    rest_norm: bool = False

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ConfigError(f"frames must be >= 1, got {self.frames}")
        if self.frame_stride < 1:
            raise ConfigError(f"frame_stride must be >= 1, got {self.frame_stride}")
        if self.width < 1:
            raise ConfigError(f"width must be >= 1, got {self.width}")
        if self.up_kernel not in (1, 3):
            raise ConfigError(f"up_kernel must be 1 or 3, got {self.up_kernel}")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.rest_norm and not self.rest_input:
            raise ConfigError("rest_norm needs rest_input (a rest image to normalise against)")

    @property
    def span(self) -> int:
        """Consecutive camera frames one input covers: the newest, and ``frames - 1``
        more every ``frame_stride`` frames back (``frames`` when the stride is 1)."""
        return (self.frames - 1) * self.frame_stride + 1

    @property
    def inputs(self) -> int:
        """Images in one model input: the rest image first (rest-referenced models), then
        the ``span`` frames of the window."""
        return self.span + int(self.rest_input)


def require_paths(config: Any, *names: str) -> None:
    """Check that each named field of a frozen config is a non-empty path and store it as
    str (ConfigError naming the field otherwise)."""
    for name in names:
        value = getattr(config, name)
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            raise ConfigError(f"{name} must be a path, got {value!r}")
        object.__setattr__(config, name, str(value))


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML config file, with an error naming the file if it is malformed."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML ({e})") from None
