"""Press plans: where and how deep the finger presses, in order, seeded.

A :class:`PressPlan` (a frozen dataclass, from code, a TOML file or a simulated rig's
settings) lists its :class:`PressTarget` objects with :meth:`PressPlan.targets`:
calibration presses at the centre first, then presses at random (uniform, seeded) or
grid locations (``PATTERNS``), like the reference (reference-facts section 5), or the
``"calibration"`` layout for few presses: positions and depths from a seeded
low-discrepancy sequence (:func:`low_discrepancy`), so any N presses - and every first
part of them - cover the pad and the force range evenly.
:meth:`PressPlan.duration_s` says how long the plan takes on the printer.
:func:`envelope_for` gives the safety envelope around a plan; :func:`check_plan` refuses
a plan that leaves a printer's envelope, before anything moves.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.config import REFERENCE_CENTRE_XY_MM, ConfigError, _Serializable, load_toml
from beadsight.devices.base import Printer, SafetyError
from beadsight.devices.envelope import SafetyEnvelope

PATTERNS = ("random", "grid", "calibration")
# Positions: the R2 sequence (Roberts 2018), step (1/p, 1/p^2) with p the plastic number
# (p^3 = p + 1), the 2-D additive sequence of lowest discrepancy; depths: the golden-ratio
# sequence, step 1/phi. Both are even for any count and for every first part.
PLASTIC = 1.324717957244746
GOLDEN = 1.618033988749895
SEQUENCE_STEP = (1 / PLASTIC, 1 / PLASTIC**2, 1 / GOLDEN)  # x, y, depth
SEQUENCE_START = 0.5
MM_PER_MIN = 60.0  # feed rates are mm/min; durations in seconds


@dataclass(frozen=True)
class PressTarget:
    """One press: its index, where (absolute printer mm) and whether it is a calibration press."""

    index: int
    x_mm: float
    y_mm: float
    z_mm: float
    kind: str  # "calibration" or "press"


@dataclass(frozen=True)
class PressPlan(_Serializable):
    """Where and how deep to press. Defaults: the reference pattern (reference-facts 5).

    Calibration presses (at the centre, mid-depth) come first, then ``presses`` presses
    at random (uniform within +-``range_mm`` in X and Y, seeded) or grid locations, each
    with a depth drawn uniformly from ``z_press_mm``.
    """

    presses: int = 500  # data presses (calibration presses come on top)
    pattern: str = "random"  # "random" (uniform), "grid" (row by row) or "calibration"
    seed: int = 0  # seeds locations and depths: the same seed gives the same plan
    centre_xy_mm: tuple[float, float] = REFERENCE_CENTRE_XY_MM  # printer XY of sensor centre
    range_mm: float = 13.75  # presses within +-this of the centre, X and Y
    z_clear_mm: float = 137.5  # printer Z for travel between presses
    z_press_mm: tuple[float, float] = (127.0, 128.0)  # press depth Z range (uniform)
    travel_feed_mm_min: float = 700.0  # G1 F700: travel and rise
    position_feed_mm_min: float = 3000.0  # after homing: rise and go over the sensor
    press_feed_mm_min: float = 200.0  # G1 F200: descent
    dwell_ms: float = 1000.0  # G4 P1000 at the bottom
    settle_ms: float = 500.0  # G4 at the clear height after each press (force back to zero)
    calibration_presses: int = 3  # presses at the centre before the plan
    descend_step_mm: float = 0.25  # descent step below check_below_z_mm (force checked between)
    check_below_z_mm: float | None = None  # None: 3 mm above the highest press Z

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_xy_mm", tuple(float(v) for v in self.centre_xy_mm))
        object.__setattr__(self, "z_press_mm", tuple(float(v) for v in self.z_press_mm))
        if self.presses < 0 or self.calibration_presses < 0:
            raise ConfigError("presses and calibration_presses must be >= 0")
        if self.pattern not in PATTERNS:
            raise ConfigError(f"pattern must be one of {PATTERNS}, got {self.pattern!r}")
        if len(self.centre_xy_mm) != 2 or len(self.z_press_mm) != 2:
            raise ConfigError("centre_xy_mm and z_press_mm must have two values each")
        lo, hi = self.z_press_mm
        if not lo <= hi < self.z_clear_mm:
            raise ConfigError(
                f"z_press_mm {self.z_press_mm} must be an increasing range below z_clear_mm "
                f"({self.z_clear_mm})"
            )
        if not self.range_mm >= 0:
            raise ConfigError(f"range_mm must be >= 0, got {self.range_mm}")
        for name in (
            "travel_feed_mm_min",
            "position_feed_mm_min",
            "press_feed_mm_min",
            "descend_step_mm",
        ):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.dwell_ms < 0 or self.settle_ms < 0:
            raise ConfigError("dwell_ms and settle_ms must be >= 0")

    @property
    def step_start_z_mm(self) -> float:
        """Z below which the descent is stepped and the force checked."""
        if self.check_below_z_mm is not None:
            return min(self.check_below_z_mm, self.z_clear_mm)
        return min(self.z_press_mm[1] + 3.0, self.z_clear_mm)

    @property
    def total(self) -> int:
        return self.calibration_presses + self.presses

    def targets(self) -> list[PressTarget]:
        """Every press of the plan, in order (deterministic for a seed)."""
        rng = np.random.default_rng(self.seed)
        cx, cy = self.centre_xy_mm
        lo, hi = self.z_press_mm
        out = [
            PressTarget(k, cx, cy, (lo + hi) / 2, "calibration")
            for k in range(self.calibration_presses)
        ]
        if self.pattern == "calibration":
            unit = low_discrepancy(self.presses, self.seed)  # (n, 3) in [0, 1)
            xy = (2 * unit[:, :2] - 1) * self.range_mm
            depths = lo + unit[:, 2] * (hi - lo)
        else:
            xy = self._xy(rng)
            depths = rng.uniform(lo, hi, size=self.presses)
        base = self.calibration_presses
        out += [
            PressTarget(base + k, cx + float(dx), cy + float(dy), float(z), "press")
            for k, ((dx, dy), z) in enumerate(zip(xy, depths, strict=True))
        ]
        return out

    def _xy(self, rng: np.random.Generator) -> np.ndarray:
        """(presses, 2) offsets from the centre, mm: random or grid."""
        if self.pattern == "random":
            return rng.uniform(-self.range_mm, self.range_mm, size=(self.presses, 2))
        side = max(1, math.ceil(math.sqrt(self.presses)))
        axis = np.linspace(-self.range_mm, self.range_mm, side) if side > 1 else np.zeros(1)
        gx, gy = np.meshgrid(axis, axis[::-1])
        return np.stack([gx.ravel(), gy.ravel()], axis=1)[: self.presses]

    def duration_s(self) -> float:
        """Seconds the plan's presses take on the printer, from its moves at their feed rates
        (travel at the clear height, descent, dwell, rise, settle); acceleration, the
        stepped descent's pauses for force checks, homing and taring come on top."""
        cx, cy = self.centre_xy_mm
        total, x, y = 0.0, cx, cy
        for t in self.targets():
            travel = math.hypot(t.x_mm - x, t.y_mm - y)
            depth = self.z_clear_mm - t.z_mm
            total += MM_PER_MIN * (
                travel / self.travel_feed_mm_min
                + depth / self.press_feed_mm_min
                + depth / self.travel_feed_mm_min
            )
            total += (self.dwell_ms + self.settle_ms) / 1000.0
            x, y = t.x_mm, t.y_mm
        return total

    @classmethod
    def from_toml(cls, path: str | Path, **overrides: Any) -> PressPlan:
        """Plan from a TOML file (keys as the fields; a ``[plan]`` table also works);
        ``overrides`` (non-None) win."""
        data = load_toml(path)
        data = data.get("plan", data)
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ConfigError(f"{path}: unknown plan field(s) {sorted(unknown)}")
        data.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls.from_dict(data)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{path}: {e}") from None

    @classmethod
    def for_simulator(cls, sim_config: Any, **overrides: Any) -> PressPlan:
        """The reference pattern on a simulated rig (its centre, heights and feeds)."""
        kwargs = {
            "centre_xy_mm": sim_config.centre_xy_mm,
            "range_mm": sim_config.press_range_mm,
            "z_clear_mm": sim_config.clear_z_mm,
            "z_press_mm": sim_config.press_z_range_mm,
            "travel_feed_mm_min": sim_config.travel_feed_mm_min,
            "press_feed_mm_min": sim_config.descend_feed_mm_min,
            "dwell_ms": sim_config.dwell_s * 1000.0,
            "settle_ms": sim_config.pause_s * 1000.0,
        }
        kwargs.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**kwargs)


def low_discrepancy(n: int, seed: int) -> np.ndarray:
    """(n, 3) points in [0, 1)^3: x, y (the R2 sequence) and depth (golden ratio) of n presses.

    Any n of them, and every first part, spread evenly, without the clusters
    and gaps of uniform random points: from its start at 0.5, every n >= 4 has a point in
    each quadrant of the pad, every n >= 8 one in each quarter of the depth range (checked
    up to 300 in tests/rig). The seed picks one of 16 symmetric layouts (a rotation or
    mirror of the pad, depths reversed or not), which keep those properties.
    """
    k = np.arange(1, n + 1, dtype=np.float64)[:, None]
    u = (SEQUENCE_START + k * np.asarray(SEQUENCE_STEP)[None]) % 1.0
    x, y, z = (u[:, 0] - 0.5, u[:, 1] - 0.5, u[:, 2])
    for _ in range(seed % 4):  # quarter turns of the pad
        x, y = -y, x
    if (seed // 4) % 2:  # mirror
        x = -x
    if (seed // 8) % 2:  # deep presses first
        z = 1.0 - z
    return np.clip(np.stack([x + 0.5, y + 0.5, z], axis=1), 0.0, 1.0)


def envelope_for(plan: PressPlan) -> SafetyEnvelope:
    """A safety envelope around the plan's sensor centre: the default margins (floor
    126.5 mm, clear 135 mm, +-15 mm) unless the plan goes beyond them."""
    default = SafetyEnvelope(centre_xy_mm=plan.centre_xy_mm)
    return SafetyEnvelope(
        centre_xy_mm=plan.centre_xy_mm,
        xy_half_range_mm=max(default.xy_half_range_mm, plan.range_mm + 1.0),
        z_floor_mm=min(default.z_floor_mm, plan.z_press_mm[0] - 0.5),
        z_clear_mm=min(default.z_clear_mm, plan.z_clear_mm),
    )


def check_plan(printer: Printer, plan: PressPlan, targets: list[PressTarget]) -> None:
    """ConfigError naming the first press whose path leaves the printer's safety envelope."""
    envelope = getattr(printer, "envelope", None)
    if envelope is None:
        return
    name = getattr(printer, "name", "printer")
    for t in targets:
        for z in (plan.z_clear_mm, t.z_mm):
            try:
                envelope.check_point((t.x_mm, t.y_mm, z), device=name)
            except SafetyError as e:
                raise ConfigError(f"press plan, press {t.index}: {e.detail}") from None
