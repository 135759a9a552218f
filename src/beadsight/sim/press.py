"""The printer's presses: the reference pattern, press profiles, and the motion through one press.

A reference press cycle (reference-facts section 5): at clear Z the printer moves to
the press XY at the travel feed (F700), descends to the press Z at F200, dwells 1 s
(G4 P1000), rises back to clear Z at F700, and pauses briefly before the next
command. Positions are millimetres from the sensor centre (printer frame) in X
and Y, and absolute printer Z. Moves run at their programmed feed (a 3D
printer's acceleration at these feeds adds well under 0.1 s and is ignored).

A :class:`Press` can also carry its own *profile*, as G-code a rig can send: a dwell
of its own (a long hold), a slow loading ramp (the last ``RAMP_START_ABOVE_SURFACE_MM``
above the surface and the descent into the pouch at ``ramp_feed_mm_min``), a slow
unloading ramp (``release_feed_mm_min``) and :class:`HoldMove` s, changes of depth while
held (a step at a fast feed, a slow drift at a feed of a few mm/min), each followed by a
dwell. :func:`draw_profile` draws them for ``profile="mixed"`` sessions.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from beadsight.errors import ConfigError
from beadsight.sim.config import PRESS_PROFILES, SimConfig

MM_MIN_PER_MM_S = 60.0  # feeds are mm/min; divide by this for mm/s
RAMP_START_ABOVE_SURFACE_MM = 0.25  # a slow ramp starts (and a slow release ends) this high
#   above the pouch surface; above it the finger moves at the descend / rise feed

# "adjust": a change of depth while the press is held (a HoldMove's move)
PHASES = ("travel", "descend", "dwell", "adjust", "rise", "pause")

PROFILES = PRESS_PROFILES  # the press profiles a session can draw (see draw_profile)

# --- the "mixed" profile: what each kind of press is drawn from ---------------------------
# kind, probability. Expected length of a press (default rig; 2000 drawn presses, seed 0):
# 16.8 s (503 frames at 30 fps), 2.5x the reference press (6.6 s); shares of the frames:
# long holds 37 %, reference 20 %, holds 20 %, changing 15 %, ramps 8 %.
MIXED_KINDS = (
    ("reference", 0.50),  # the reference press (F200, 1 s dwell, F700)
    ("hold", 0.20),  # a steady hold of HOLD_S
    ("long_hold", 0.08),  # a steady hold of LONG_HOLD_S (the issue's >= 60 s)
    ("ramp", 0.10),  # a slow loading ramp, half of them with a slow release, then RAMP_HOLD_S
    ("changing", 0.12),  # depth steps and slow drifts while held
)
HOLD_S = (3.0, 20.0)  # dwell of a "hold" press, s (uniform)
LONG_HOLD_S = (60.0, 90.0)  # dwell of a "long_hold" press, s (uniform)
RAMP_FEED_MM_MIN = (20.0, 60.0)  # loading / unloading feed of a "ramp" press (uniform)
RAMP_HOLD_S = (1.0, 10.0)  # dwell of a "ramp" press at the bottom, s (uniform)
SLOW_RELEASE_PROBABILITY = 0.5  # share of "ramp" presses that also unload slowly
CHANGE_FIRST_DWELL_S = (2.0, 6.0)  # a "changing" press dwells this long before its first move
CHANGE_MOVES = (1, 3)  # depth changes per "changing" press (inclusive)
STEP_PROBABILITY = 0.5  # share of the changes that are steps (the others: slow drifts)
STEP_FEED_MM_MIN = (100.0, 300.0)  # feed of a depth step (uniform)
STEP_MM = (0.15, 0.5)  # size of a depth step, mm (uniform)
DRIFT_FEED_MM_MIN = (2.0, 8.0)  # feed of a slow drift (uniform): 0.03-0.13 mm/s
DRIFT_MM = (0.2, 0.5)  # size of a slow drift, mm (uniform)
CHANGE_DWELL_S = (1.0, 5.0)  # dwell after each change, s (uniform)
# Held depths stay in [this, the deepest press depth of the config]: shallow enough for a
# light load, deep enough that a step's viscoelastic undershoot keeps the force well above
# the contact-release threshold (a press is never split in two by its own step).
MIN_HELD_DEPTH_MM = 0.6
MIN_CHANGE_MM = 0.1  # a change clipped to less than this goes the other way instead


@dataclass(frozen=True)
class HoldMove:
    """A change of depth while a press is held: move the finger to ``z_mm`` (printer Z,
    below the pouch surface) at ``feed_mm_min``, then dwell ``dwell_s`` seconds."""

    z_mm: float
    feed_mm_min: float
    dwell_s: float = 0.0

    def __post_init__(self) -> None:
        _need_number(self.z_mm, "HoldMove.z_mm", positive=False)
        _need_number(self.feed_mm_min, "HoldMove.feed_mm_min", positive=True)
        _need_number(self.dwell_s, "HoldMove.dwell_s", positive=False, non_negative=True)


@dataclass(frozen=True)
class Press:
    """One commanded press: finger XY (mm from the sensor centre) and bottom Z (printer mm).

    The rest is the press's profile (defaults: the reference press). dwell_s: time held
    at ``z_mm`` (s; None: the config's ``dwell_s``); ramp_feed_mm_min: the feed of the
    descent's last part, from ``RAMP_START_ABOVE_SURFACE_MM`` above the surface (None:
    the whole descent at the config's descend feed); hold_moves: depth changes after the
    dwell, in order; release_feed_mm_min: the feed of the rise's first part, up to
    ``RAMP_START_ABOVE_SURFACE_MM`` above the surface (None: the config's rise feed).
    """

    x_mm: float
    y_mm: float
    z_mm: float
    dwell_s: float | None = None
    ramp_feed_mm_min: float | None = None
    hold_moves: tuple[HoldMove, ...] = ()
    release_feed_mm_min: float | None = None

    def __post_init__(self) -> None:
        for name in ("x_mm", "y_mm", "z_mm"):
            _need_number(getattr(self, name), f"Press.{name}", positive=False)
        if self.dwell_s is not None:
            _need_number(self.dwell_s, "Press.dwell_s", positive=False, non_negative=True)
        for name in ("ramp_feed_mm_min", "release_feed_mm_min"):
            if getattr(self, name) is not None:
                _need_number(getattr(self, name), f"Press.{name}", positive=True)
        moves = tuple(self.hold_moves)
        if not all(isinstance(m, HoldMove) for m in moves):
            raise ConfigError(f"Press.hold_moves must be HoldMove objects, got {moves!r}")
        object.__setattr__(self, "hold_moves", moves)

    @property
    def xy_mm(self) -> np.ndarray:
        return np.array([self.x_mm, self.y_mm], dtype=np.float64)

    @property
    def is_reference(self) -> bool:
        """True if the press follows the reference pattern (no profile of its own)."""
        return (
            self.dwell_s is None
            and self.ramp_feed_mm_min is None
            and not self.hold_moves
            and self.release_feed_mm_min is None
        )


def _need_number(value, name: str, *, positive: bool, non_negative: bool = False) -> None:
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.floating, np.integer))
    ok = ok and math.isfinite(value)
    if ok and positive:
        ok = value > 0
    if ok and non_negative:
        ok = value >= 0
    if not ok:
        expected = "> 0" if positive else ">= 0" if non_negative else "finite"
        raise ConfigError(f"{name} must be a number {expected}, got {value!r}")


def sample_presses(config: SimConfig, count: int, rng: np.random.Generator) -> list[Press]:
    """``count`` presses uniform within +-press_range_mm and press_z_range_mm."""
    r = config.press_range_mm
    lo, hi = config.press_z_range_mm
    xy = rng.uniform(-r, r, size=(count, 2))
    z = rng.uniform(lo, hi, size=count)
    return [Press(float(a), float(b), float(c)) for (a, b), c in zip(xy, z, strict=True)]


def check_profile(profile: str) -> str:
    """``profile`` if it is one of :data:`PROFILES`, else a ConfigError naming them."""
    if profile not in PROFILES:
        raise ConfigError(f"profile must be one of {PROFILES}, got {profile!r}")
    return profile


def draw_profile(config: SimConfig, press: Press, profile: str, rng: np.random.Generator) -> Press:
    """``press`` (XY and bottom Z as drawn for the reference pattern) with a profile drawn
    from ``profile`` using ``rng``.

    "reference": ``press`` unchanged, and nothing is drawn from ``rng``. "mixed": one of
    :data:`MIXED_KINDS` by its probability (ranges: the constants above), so that a
    dataset of N presses holds all kinds, its frames dominated by none:

    ============  ====  ======================================================
    kind          p     profile
    ============  ====  ======================================================
    reference     0.50  the reference press
    hold          0.20  dwell 3-20 s
    long_hold     0.08  dwell 60-90 s
    ramp          0.10  load at F20-F60 (half also unload at F20-F60), dwell 1-10 s
    changing      0.12  dwell 2-6 s, then 1-3 depth changes, each a step (0.15-0.5 mm
                        at F100-F300) or a slow drift (0.2-0.5 mm at F2-F8), up or
                        down within [0.6 mm, the deepest press depth], dwell 1-5 s
    ============  ====  ======================================================

    Expected frames per press: 2.5x the reference press; long holds hold 37 % of the
    frames, reference presses 20 %. Every press ends with the finger back at clear Z and the pouch
    unloaded, so the beads re-settle (a new packing) before the next one.
    """
    check_profile(profile)
    if profile == "reference":
        return press
    kinds = [k for k, _ in MIXED_KINDS]
    p = np.array([w for _, w in MIXED_KINDS])
    kind = kinds[int(rng.choice(len(kinds), p=p / p.sum()))]
    if kind == "reference":
        return press
    if kind == "hold":
        return dataclasses.replace(press, dwell_s=float(rng.uniform(*HOLD_S)))
    if kind == "long_hold":
        return dataclasses.replace(press, dwell_s=float(rng.uniform(*LONG_HOLD_S)))
    if kind == "ramp":
        ramp = float(rng.uniform(*RAMP_FEED_MM_MIN))
        dwell = float(rng.uniform(*RAMP_HOLD_S))
        slow_release = rng.random() < SLOW_RELEASE_PROBABILITY
        release = float(rng.uniform(*RAMP_FEED_MM_MIN)) if slow_release else None
        return dataclasses.replace(
            press, dwell_s=dwell, ramp_feed_mm_min=ramp, release_feed_mm_min=release
        )
    return dataclasses.replace(
        press,
        dwell_s=float(rng.uniform(*CHANGE_FIRST_DWELL_S)),
        hold_moves=_draw_changes(config, press.z_mm, rng),
    )


def _draw_changes(config: SimConfig, z_mm: float, rng: np.random.Generator) -> tuple:
    """1-3 depth changes from bottom Z ``z_mm``, kept within the held-depth range."""
    deepest_mm = config.depth_range_mm()[1]
    lo_z = config.surface_z_mm - max(deepest_mm, MIN_HELD_DEPTH_MM)  # deepest Z
    hi_z = config.surface_z_mm - MIN_HELD_DEPTH_MM  # shallowest Z
    moves, z = [], z_mm
    for _ in range(int(rng.integers(CHANGE_MOVES[0], CHANGE_MOVES[1] + 1))):
        step = rng.random() < STEP_PROBABILITY
        size = float(rng.uniform(*(STEP_MM if step else DRIFT_MM)))
        feed = float(rng.uniform(*(STEP_FEED_MM_MIN if step else DRIFT_FEED_MM_MIN)))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        target = min(max(z + sign * size, lo_z), hi_z)
        if abs(target - z) < MIN_CHANGE_MM:  # against a limit: go the other way
            target = min(max(z - sign * size, lo_z), hi_z)
        moves.append(HoldMove(float(target), feed, float(rng.uniform(*CHANGE_DWELL_S))))
        z = target
    return tuple(moves)


class PressCycle:
    """The printer's commanded motion for one press, starting at ``start_s``.

    ``from_xy_mm`` is where the finger is (at clear Z) when the cycle starts.
    :meth:`state_at` gives the finger's XY (mm from centre), Z (printer mm) and
    the phase name at any time within the cycle. The *commanded* XY a rig logs is
    the press XY for the whole cycle (the travel command is logged when sent).
    The motion is piecewise linear: travel, descend (a slow ramp's last part at its own
    feed), dwell, then per hold move adjust and dwell, rise (a slow release's first part
    at its own feed), pause.
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
        # (duration s, Z at the segment's end, phase); XY is the target after travel
        segments = [(travel_s, clear, "travel")]
        segments += self._ramp(
            clear, press.z_mm, config.descend_feed_mm_min, press.ramp_feed_mm_min, "descend"
        )
        dwell = config.dwell_s if press.dwell_s is None else press.dwell_s
        segments.append((dwell, press.z_mm, "dwell"))
        z = press.z_mm
        for move in press.hold_moves:
            segments.append(
                (abs(move.z_mm - z) / (move.feed_mm_min / MM_MIN_PER_MM_S), move.z_mm, "adjust")
            )
            segments.append((move.dwell_s, move.z_mm, "dwell"))
            z = move.z_mm
        segments += self._ramp(z, clear, config.rise_feed_mm_min, press.release_feed_mm_min, "rise")
        segments.append((config.pause_s, clear, "pause"))
        durations = [d for d, _, _ in segments]
        self._times = self.start_s + np.concatenate([[0.0], np.cumsum(durations)])
        n = len(segments)
        self._x = np.array([start[0]] + [target[0]] * n)
        self._y = np.array([start[1]] + [target[1]] * n)
        self._z = np.array([clear] + [z_end for _, z_end, _ in segments])
        self._phases = tuple(phase for _, _, phase in segments)
        self.end_s = float(self._times[-1])

    def _ramp(
        self, z_from: float, z_to: float, feed: float, slow_feed: float | None, phase: str
    ) -> list[tuple[float, float, str]]:
        """A vertical move at ``feed``, with the part below the ramp start at ``slow_feed``."""
        cfg = self.config
        ramp_z = min(cfg.surface_z_mm + RAMP_START_ABOVE_SURFACE_MM, cfg.clear_z_mm)
        lo, hi = min(z_from, z_to), max(z_from, z_to)
        if slow_feed is None or not lo < ramp_z < hi:
            if slow_feed is not None and hi <= ramp_z:  # all of it below the ramp start
                feed = slow_feed
            return [(abs(z_to - z_from) / (feed / MM_MIN_PER_MM_S), z_to, phase)]
        fast = (hi - ramp_z) / (feed / MM_MIN_PER_MM_S)
        slow = (ramp_z - lo) / (slow_feed / MM_MIN_PER_MM_S)
        if z_to < z_from:  # down: fast, then slow
            return [(fast, ramp_z, phase), (slow, z_to, phase)]
        return [(slow, ramp_z, phase), (fast, z_to, phase)]

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
        return xy, z, self._phases[min(max(k, 0), len(self._phases) - 1)]

    def contact_window_s(self) -> tuple[float, float]:
        """Times at which the finger passes the pouch surface on the way down and, last, up.

        (The end of the descent twice if the press never goes below the surface.)"""
        surface = self.config.surface_z_mm
        t, z = self._times, self._z
        below = np.flatnonzero(z < surface)
        if len(below) == 0:
            end_descent = t[self._phases.index("dwell")]
            return float(end_descent), float(end_descent)
        first, last = int(below[0]), int(below[-1])  # points; their neighbours are above

        def crossing(a: int, b: int) -> float:
            return float(t[a] + (surface - z[a]) / (z[b] - z[a]) * (t[b] - t[a]))

        return crossing(first - 1, first), crossing(last, last + 1)
