"""The reference press pattern and the printer's motion through one press.

A press cycle (reference-facts section 5): at clear Z the printer moves to the
press XY at the travel feed (F700), descends to the press Z at F200, dwells 1 s
(G4 P1000), rises back to clear Z at F700, and pauses briefly before the next
command. Positions are millimetres from the sensor centre (printer frame) in X
and Y, and absolute printer Z. Moves run at their programmed feed (a 3D
printer's acceleration at these feeds adds well under 0.1 s and is ignored).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beadsight.sim.config import SimConfig

MM_MIN_PER_MM_S = 60.0  # feeds are mm/min; divide by this for mm/s

PHASES = ("travel", "descend", "dwell", "rise", "pause")


@dataclass(frozen=True)
class Press:
    """One commanded press: finger XY (mm from the sensor centre) and bottom Z (printer mm)."""

    x_mm: float
    y_mm: float
    z_mm: float

    @property
    def xy_mm(self) -> np.ndarray:
        return np.array([self.x_mm, self.y_mm], dtype=np.float64)


def sample_presses(config: SimConfig, count: int, rng: np.random.Generator) -> list[Press]:
    """``count`` presses uniform within +-press_range_mm and press_z_range_mm."""
    r = config.press_range_mm
    lo, hi = config.press_z_range_mm
    xy = rng.uniform(-r, r, size=(count, 2))
    z = rng.uniform(lo, hi, size=count)
    return [Press(float(a), float(b), float(c)) for (a, b), c in zip(xy, z, strict=True)]


class PressCycle:
    """The printer's commanded motion for one press, starting at ``start_s``.

    ``from_xy_mm`` is where the finger is (at clear Z) when the cycle starts.
    :meth:`state_at` gives the finger's XY (mm from centre), Z (printer mm) and
    the phase name at any time within the cycle. The *commanded* XY a rig logs is
    the press XY for the whole cycle (the travel command is logged when sent).
    """

    def __init__(self, config: SimConfig, press: Press, start_s: float, from_xy_mm, index: int):
        self.config = config
        self.press = press
        self.index = index
        self.start_s = float(start_s)
        start = np.asarray(from_xy_mm, dtype=np.float64)
        target = press.xy_mm
        clear = config.clear_z_mm
        travel_s = float(np.linalg.norm(target - start)) / (
            config.travel_feed_mm_min / MM_MIN_PER_MM_S
        )
        descend_s = (clear - press.z_mm) / (config.descend_feed_mm_min / MM_MIN_PER_MM_S)
        rise_s = (clear - press.z_mm) / (config.rise_feed_mm_min / MM_MIN_PER_MM_S)
        durations = [travel_s, descend_s, config.dwell_s, rise_s, config.pause_s]
        self._times = self.start_s + np.concatenate([[0.0], np.cumsum(durations)])
        self._x = np.array([start[0], target[0], target[0], target[0], target[0], target[0]])
        self._y = np.array([start[1], target[1], target[1], target[1], target[1], target[1]])
        self._z = np.array([clear, clear, press.z_mm, press.z_mm, clear, clear])
        self.end_s = float(self._times[-1])

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s

    @property
    def commanded_xy_mm(self) -> np.ndarray:
        return self.press.xy_mm

    def state_at(self, t_s: float) -> tuple[np.ndarray, float, str]:
        """Finger ``(xy_mm (2,), z_mm, phase)`` at time ``t_s`` (clamped to the cycle)."""
        t = min(max(float(t_s), self.start_s), self.end_s)
        xy = np.array([np.interp(t, self._times, self._x), np.interp(t, self._times, self._y)])
        z = float(np.interp(t, self._times, self._z))
        k = int(np.searchsorted(self._times, t, side="right")) - 1
        return xy, z, PHASES[min(max(k, 0), len(PHASES) - 1)]

    def contact_window_s(self) -> tuple[float, float]:
        """Times at which the finger passes the pouch surface on the way down and up."""
        cfg = self.config
        t_desc0, t_desc1, t_dwell1, t_rise1 = self._times[1:5]
        surface = cfg.surface_z_mm
        if self.press.z_mm >= surface:
            return t_desc1, t_desc1
        down = t_desc0 + (cfg.clear_z_mm - surface) / (cfg.clear_z_mm - self.press.z_mm) * (
            t_desc1 - t_desc0
        )
        up = t_dwell1 + (surface - self.press.z_mm) / (cfg.clear_z_mm - self.press.z_mm) * (
            t_rise1 - t_dwell1
        )
        return float(down), float(up)
