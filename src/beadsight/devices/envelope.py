"""The safety envelope: where the finger may go around the sensor (printer coordinates).

Two rules, checked on the straight path of every move before anything is sent:

1. Never below ``z_floor_mm`` (the deepest press the pouch and scale can take).
2. Below ``z_clear_mm`` (close to the sensor), the finger's XY must stay inside the box
   ``centre_xy_mm +- xy_half_range_mm``; at or above ``z_clear_mm`` XY travel is free.

Feed rates above ``max_feed_mm_min`` are refused too. The defaults match the reference
rig: sensor centre (151.8, 108.9), presses within +-13.75 mm and Z in [127, 128] mm,
travel at Z 137.5 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from beadsight.config import REFERENCE_CENTRE_XY_MM, ConfigError, _Serializable
from beadsight.devices.base import SafetyError

_EPS_MM = 1e-6  # tolerance for points exactly on the boundary

Point = tuple[float, float, float]


@dataclass(frozen=True)
class SafetyEnvelope(_Serializable):
    """Allowed finger positions in printer coordinates (mm)."""

    centre_xy_mm: tuple[float, float] = REFERENCE_CENTRE_XY_MM  # printer XY of the sensor centre
    xy_half_range_mm: float = 15.0  # below z_clear_mm, |x - cx| and |y - cy| must be <= this
    z_floor_mm: float = 126.5  # the finger never goes below this Z
    z_clear_mm: float = 135.0  # at or above this Z the finger is clear of the sensor; XY free
    max_feed_mm_min: float = 3000.0  # faster moves are refused

    def __post_init__(self) -> None:
        centre = tuple(float(v) for v in self.centre_xy_mm)
        if len(centre) != 2 or not all(math.isfinite(v) for v in centre):
            raise ConfigError(f"centre_xy_mm must be two finite numbers, got {self.centre_xy_mm}")
        object.__setattr__(self, "centre_xy_mm", centre)
        if not self.xy_half_range_mm > 0:
            raise ConfigError(f"xy_half_range_mm must be > 0, got {self.xy_half_range_mm}")
        if not self.z_floor_mm < self.z_clear_mm:
            raise ConfigError(
                f"z_floor_mm ({self.z_floor_mm}) must be below z_clear_mm ({self.z_clear_mm})"
            )
        if not self.max_feed_mm_min > 0:
            raise ConfigError(f"max_feed_mm_min must be > 0, got {self.max_feed_mm_min}")

    @classmethod
    def around_sensor(
        cls,
        centre_xy_mm: tuple[float, float],
        surface_z_mm: float,
        *,
        max_depth_mm: float = 4.0,
        clearance_mm: float = 5.0,
        xy_half_range_mm: float = 15.0,
        max_feed_mm_min: float = 3000.0,
    ) -> SafetyEnvelope:
        """Envelope for a sensor whose top surface the finger touches at ``surface_z_mm``:
        floor ``max_depth_mm`` below it, clear height ``clearance_mm`` above it."""
        return cls(
            centre_xy_mm=centre_xy_mm,
            xy_half_range_mm=xy_half_range_mm,
            z_floor_mm=surface_z_mm - max_depth_mm,
            z_clear_mm=surface_z_mm + clearance_mm,
            max_feed_mm_min=max_feed_mm_min,
        )

    def contains(self, point: Point) -> bool:
        """Whether the finger may rest at ``point`` = (x, y, z) mm."""
        try:
            self.check_point(point, device="envelope")
        except SafetyError:
            return False
        return True

    def check_point(self, point: Point, *, device: str) -> None:
        """Raise SafetyError (naming ``device``) unless the finger may rest at ``point``."""
        x, y, z = point
        if not all(math.isfinite(v) for v in point):
            raise SafetyError(
                device, f"refused move to X={x} Y={y} Z={z}: coordinates must be finite numbers"
            )
        if z < self.z_floor_mm - _EPS_MM:
            raise SafetyError(
                device,
                f"refused move to {_fmt(point)}: Z is below the safety floor Z={self.z_floor_mm:g} mm; nothing was sent",
                "raise the press depth or lower SafetyEnvelope.z_floor_mm if the sensor really sits lower",
            )
        if z < self.z_clear_mm - _EPS_MM:
            self._check_xy(x, y, point, device)

    def _check_xy(self, x: float, y: float, point: Point, device: str) -> None:
        cx, cy = self.centre_xy_mm
        dx, dy = x - cx, y - cy
        if max(abs(dx), abs(dy)) > self.xy_half_range_mm + _EPS_MM:
            raise SafetyError(
                device,
                f"refused move through {_fmt(point)}: below the clear height Z={self.z_clear_mm:g} mm the finger "
                f"must stay within +-{self.xy_half_range_mm:g} mm of the sensor centre "
                f"({cx:g}, {cy:g}), but this is {dx:+.3f}, {dy:+.3f} mm away; nothing was sent",
                "travel above z_clear_mm first, then descend over the sensor",
            )

    def check_move(
        self, start: Point | None, target: Point, feed_mm_min: float, *, device: str
    ) -> None:
        """Raise SafetyError unless the straight move ``start`` -> ``target`` stays allowed.

        start: current position, or None when unknown (refused: home first).
        """
        if not (math.isfinite(feed_mm_min) and 0 < feed_mm_min <= self.max_feed_mm_min):
            raise SafetyError(
                device,
                f"refused move to {_fmt(target)}: feed rate F{feed_mm_min:g} mm/min must be in "
                f"(0, {self.max_feed_mm_min:g}] mm/min; nothing was sent",
            )
        if start is None:
            raise SafetyError(
                device, f"refused move to {_fmt(target)}: position unknown; home the printer first"
            )
        self.check_point(target, device=device)
        if not self.contains(start) and _is_vertical_rise(start, target):
            return  # the way out of a position the envelope does not allow (e.g. after homing)
        # The part of the path below the clear height is a segment; the box is convex, so
        # checking that segment's two ends covers every point in between.
        for point in self._low_segment_ends(start, target):
            self.check_point(point, device=device)

    def _low_segment_ends(self, start: Point, target: Point) -> list[Point]:
        z0, z1 = start[2], target[2]
        clear = self.z_clear_mm
        if z0 >= clear and z1 >= clear:
            return []
        ends: list[Point] = []
        for inside, outside in ((start, target), (target, start)):
            if inside[2] < clear:
                ends.append(inside)
            else:  # where the path crosses the clear height, just below it
                frac = (inside[2] - clear) / (inside[2] - outside[2])
                crossing = tuple(a + frac * (b - a) for a, b in zip(inside, outside, strict=True))
                ends.append((crossing[0], crossing[1], clear - _EPS_MM * 2))
        return ends


def _is_vertical_rise(start: Point, target: Point) -> bool:
    same_xy = abs(start[0] - target[0]) <= _EPS_MM and abs(start[1] - target[1]) <= _EPS_MM
    return same_xy and target[2] >= start[2]


def _fmt(point: Point) -> str:
    return "X={:.3f} Y={:.3f} Z={:.3f}".format(*point)
