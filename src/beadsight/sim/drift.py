"""Drift of a sensor in use, applied to simulated frames: settling beads, light, a camera bump.

Three kinds, each on or off, combinable, each a function of the time since the session
started (s):

* ``settle`` - the beads creep towards the pouch centre as they settle:
  ``settle_mm * (1 - exp(-t / settle_tau_s))`` at the edge midpoints (``r`` = half the
  field of view), proportional to the distance from the centre (no global shift).
* ``light`` - the LEDs (or the room) dim and change colour: brightness ×
  ``1 + light_change * ramp``, red × ``1 + light_tint * ramp``, blue ×
  ``1 - light_tint * ramp``, ``ramp`` going 0 -> 1 from ``light_start_s`` over
  ``light_ramp_s``.
* ``bump`` - the camera is knocked at ``bump_at_s``: from then on the image is shifted by
  ``bump_mm`` along ``bump_angle_deg`` (0: the image's +x, 90: its +y).

:func:`parse_drift` reads the ``--sim-drift`` text: kinds and ``field=value`` pairs
separated by commas (``settle``, ``light,light_change=-0.5``, ``bump,bump_at_s=9``); a
field enables its kind. :class:`DriftRenderer` applies a :class:`DriftSpec` to frames.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from beadsight.errors import ConfigError

KINDS = ("settle", "light", "bump")
_TOKEN_HELP = "kinds settle, light, bump and field=value pairs, comma separated"


@dataclass(frozen=True)
class DriftSpec:
    """Which drift the simulator adds (see the module docstring); all off by default."""

    settle: bool = False
    settle_mm: float = 1.2  # creep at the edge midpoints once settled, mm
    settle_tau_s: float = 20.0  # time constant of the settling, s
    light: bool = False
    light_change: float = -0.4  # brightness change at the end of the ramp (fraction)
    light_tint: float = 0.2  # red up, blue down by this fraction at the end of the ramp
    light_start_s: float = 0.0  # the ramp starts, s
    light_ramp_s: float = 30.0  # the ramp takes, s
    bump: bool = False
    bump_at_s: float = 5.0  # the camera is knocked at, s
    bump_mm: float = 1.0  # image shift after the bump, mm on the pouch
    bump_angle_deg: float = 0.0  # direction of the shift in the image (0: +x)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type in (bool, "bool"):
                if not isinstance(value, bool):
                    raise ConfigError(f"drift {f.name} must be true or false, got {value!r}")
            elif isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"drift {f.name} must be a number, got {value!r}")
            elif not math.isfinite(value):
                raise ConfigError(f"drift {f.name} must be finite, got {value!r}")
        for name in ("settle_tau_s", "light_ramp_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"drift {name} must be > 0, got {getattr(self, name)!r}")
        for name in ("light_start_s", "bump_at_s", "bump_mm"):
            if getattr(self, name) < 0:
                raise ConfigError(f"drift {name} must be >= 0, got {getattr(self, name)!r}")
        if not -1.0 < self.light_change:
            raise ConfigError(f"drift light_change must be > -1, got {self.light_change!r}")
        if not 0.0 <= self.light_tint < 1.0:
            raise ConfigError(f"drift light_tint must be in [0, 1), got {self.light_tint!r}")

    @property
    def any(self) -> bool:
        return self.settle or self.light or self.bump

    def describe(self) -> str:
        """The spec as :func:`parse_drift` reads it (kinds on, fields that differ)."""
        default = DriftSpec()
        parts = [k for k in KINDS if getattr(self, k)]
        for f in dataclasses.fields(self):
            if f.name not in KINDS and getattr(self, f.name) != getattr(default, f.name):
                parts.append(f"{f.name}={getattr(self, f.name):g}")
        return ",".join(parts) or "none"

    def settle_at(self, t_s: float) -> float:
        """Creep at the edge midpoints at ``t_s``, mm (0 without ``settle``)."""
        if not self.settle:
            return 0.0
        return self.settle_mm * (1.0 - math.exp(-max(t_s, 0.0) / self.settle_tau_s))

    def light_ramp_at(self, t_s: float) -> float:
        """How far the light ramp has gone at ``t_s`` (0..1; 0 without ``light``)."""
        if not self.light:
            return 0.0
        return min(max((t_s - self.light_start_s) / self.light_ramp_s, 0.0), 1.0)

    def bump_at(self, t_s: float) -> float:
        """Image shift at ``t_s``, mm (0 before the bump or without ``bump``)."""
        return self.bump_mm if self.bump and t_s >= self.bump_at_s else 0.0


def parse_drift(text: str | DriftSpec | None) -> DriftSpec:
    """A :class:`DriftSpec` from ``--sim-drift`` text (None or "" or "none": no drift).

    Raises ConfigError naming the unknown kind or field, or the bad value.
    """
    if isinstance(text, DriftSpec):
        return text
    if text is None or not str(text).strip() or str(text).strip().lower() == "none":
        return DriftSpec()
    fields = {f.name: f for f in dataclasses.fields(DriftSpec)}
    changes: dict[str, bool | float] = {}
    for token in (t.strip() for t in str(text).split(",")):
        if not token:
            continue
        name, eq, value = (part.strip() for part in token.partition("="))
        if name not in fields:
            known = ", ".join(n for n in fields if n not in KINDS)
            raise ConfigError(
                f"--sim-drift: unknown {'field' if eq else 'kind'} {name!r} in {text!r} "
                f"({_TOKEN_HELP}; kinds: {', '.join(KINDS)}; fields: {known})"
            )
        if not eq:
            if name not in KINDS:
                raise ConfigError(f"--sim-drift: {name!r} needs a value ({name}=...)")
            changes[name] = True
            continue
        if name in KINDS:
            raise ConfigError(f"--sim-drift: {name!r} is a kind; write it without a value")
        try:
            changes[name] = float(value)
        except ValueError:
            raise ConfigError(f"--sim-drift: {name} must be a number, got {value!r}") from None
        changes[next(k for k in KINDS if name.startswith(k))] = True  # a field enables its kind
    return DriftSpec(**changes)


class DriftRenderer:
    """Applies a :class:`DriftSpec` to (S, S, 3) uint8 RGB sensor-space frames.

    image_size_px: S; sensor_size_mm: the side of the field of view the frames show.
    """

    def __init__(self, spec: DriftSpec, image_size_px: int, sensor_size_mm: float):
        self.spec = spec
        self.px_per_mm = image_size_px / sensor_size_mm
        centre = (image_size_px - 1) / 2.0
        grid = np.arange(image_size_px, dtype=np.float32) - centre
        self._gx, self._gy = np.meshgrid(grid, grid)  # px from the centre
        self._centre = centre
        self._half_px = image_size_px / 2.0

    def apply(self, frame_rgb: np.ndarray, t_s: float) -> np.ndarray:
        """``frame_rgb`` (S, S, 3) uint8 RGB as the drifted sensor shows it at ``t_s``."""
        spec = self.spec
        if not spec.any:
            return frame_rgb
        out = self._warp(frame_rgb, spec.settle_at(t_s), spec.bump_at(t_s))
        ramp = spec.light_ramp_at(t_s)
        if ramp > 0:
            gain = 1.0 + spec.light_change * ramp
            tint = spec.light_tint * ramp
            scale = np.array([gain * (1 + tint), gain, gain * (1 - tint)], dtype=np.float32)
            out = np.clip(out.astype(np.float32) * scale, 0, 255).astype(np.uint8)
        return out

    def _warp(self, frame: np.ndarray, settle_mm: float, bump_mm: float) -> np.ndarray:
        if settle_mm == 0 and bump_mm == 0:
            return frame
        # content moves inward by settle * r / half: sample further out
        k = settle_mm * self.px_per_mm / self._half_px
        angle = math.radians(self.spec.bump_angle_deg)
        shift_x = bump_mm * self.px_per_mm * math.cos(angle)
        shift_y = bump_mm * self.px_per_mm * math.sin(angle)
        map_x = self._gx * (1 + k) + self._centre - shift_x
        map_y = self._gy * (1 + k) + self._centre - shift_y
        return cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
