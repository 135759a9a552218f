"""Per-frame labels of a raw recording: force and position at every frame time.

* **Clocks.** Frames, scale readings and printer commands are all stamped by the
  host. When every stream carries the monotonic clock (this project's format) it is
  used for alignment (it never jumps with NTP); otherwise unix time (reference
  format).
* **Force per frame** by interpolating the scale log at each frame time:
  ``"pchip"`` (default; a shape-preserving piecewise cubic: no overshoot or ringing
  around the sharp onset of a press, never below the smallest neighbouring
  reading), ``"cubic"`` (an interpolating cubic spline, like the reference) or
  ``"linear"``. Never extrapolated: frames before the first or after the last
  reading are invalid, and so are frames inside a gap of more than
  ``max_force_gap_s`` between readings.
* **Position per frame**: zero-order hold of the last executed printer command
  (its XY in mm from the sensor centre). Frames before the first command, or
  whose last command is not a data move (homing, parking; x = y = -1 in the
  reference log), are invalid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beadsight.data.process.config import FORCE_INTERPOLATIONS, ProcessConfig
from beadsight.data.recording import Recording

# Reasons a frame is invalid (one per frame; the first that applies, in this order).
REASONS = (
    "before_force_log",
    "after_force_log",
    "force_gap",
    "force_over_capacity",
    "no_printer_log",
    "before_first_move",
    "non_data_move",
)


def _strictly_increasing(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort by time and average readings that share a timestamp."""
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    uniq, inverse, counts = np.unique(t, return_inverse=True, return_counts=True)
    if len(uniq) == len(t):
        return t, values
    sums = np.bincount(inverse, weights=values, minlength=len(uniq))
    return uniq, sums / counts


def interpolate_force(
    t_force: np.ndarray,
    force_n: np.ndarray,
    t_frames: np.ndarray,
    *,
    method: str = "pchip",
    max_gap_s: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Force at each frame time; never extrapolates.

    t_force: (M,) s; force_n: (M,) N; t_frames: (N,) s (same clock).
    returns: force (N,) float64 N (NaN where invalid) and a reason code (N,) int8:
    0 valid, 1 before the first reading, 2 after the last, 3 inside a gap longer
    than ``max_gap_s``.
    """
    from scipy.interpolate import CubicSpline, PchipInterpolator

    t_frames = np.asarray(t_frames, np.float64)
    force = np.full(len(t_frames), np.nan)
    reason = np.zeros(len(t_frames), np.int8)
    ok = np.isfinite(t_force) & np.isfinite(force_n)
    t, f = _strictly_increasing(
        np.asarray(t_force, np.float64)[ok], np.asarray(force_n, np.float64)[ok]
    )
    if len(t) < 2:
        reason[:] = 1
        return force, reason
    reason[t_frames < t[0]] = 1
    reason[t_frames > t[-1]] = 2
    inside = reason == 0
    idx = np.clip(np.searchsorted(t, t_frames[inside], side="right"), 1, len(t) - 1)
    gap = (t[idx] - t[idx - 1]) > max_gap_s
    inside_idx = np.flatnonzero(inside)
    reason[inside_idx[gap]] = 3
    good = reason == 0
    if method == "linear":
        force[good] = np.interp(t_frames[good], t, f)
    elif method == "cubic":
        force[good] = CubicSpline(t, f, extrapolate=False)(t_frames[good])
    elif method == "pchip":
        force[good] = PchipInterpolator(t, f, extrapolate=False)(t_frames[good])
    else:
        raise ValueError(f"method must be one of {FORCE_INTERPOLATIONS}, got {method!r}")
    return force, reason


def hold_positions(
    t_moves: np.ndarray, offset_mm: np.ndarray, is_data: np.ndarray, t_frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order hold of the last executed command's XY at each frame time.

    t_moves: (K,) s; offset_mm: (K, 2) mm from the sensor centre; is_data: (K,) bool.
    returns: position (N, 2) float64 mm (NaN where invalid) and a reason code (N,) int8:
    0 valid, 1 no printer log, 2 before the first command, 3 the last command is not
    a data move. A command exactly at a frame's time counts as executed.
    """
    n = len(t_frames)
    position = np.full((n, 2), np.nan)
    reason = np.zeros(n, np.int8)
    if len(t_moves) == 0:
        reason[:] = 1
        return position, reason
    order = np.argsort(t_moves, kind="stable")
    t, xy, data = t_moves[order], offset_mm[order], np.asarray(is_data, bool)[order]
    idx = np.searchsorted(t, t_frames, side="right") - 1
    reason[idx < 0] = 2
    has = idx >= 0
    held = idx[has]
    ok_data = data[held] & np.isfinite(xy[held]).all(axis=1)
    rows = np.flatnonzero(has)
    reason[rows[~ok_data]] = 3
    position[rows[ok_data]] = xy[held[ok_data]]
    return position, reason


@dataclass
class FrameLabels:
    """Per logged frame (recording order): t_unix (N,) s, force_n (N,) N, position_mm
    (N, 2) mm, valid (N,) bool, reason (N,) int8 index+1 into REASONS (0 = valid)."""

    t_unix: np.ndarray
    force_n: np.ndarray
    position_mm: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    clock: str


def frame_labels(
    rec: Recording, config: ProcessConfig, over_capacity: np.ndarray | None = None
) -> FrameLabels:
    """Align the streams of ``rec`` and label every logged frame.

    over_capacity: (M,) bool per force reading (see :mod:`beadsight.data.plausibility`):
    those readings are not used, and frames whose force would come from them are invalid.
    """
    clock = "monotonic" if rec.has_monotonic else "unix"
    key = "t_mono" if clock == "monotonic" else "t_unix"
    t_frames = getattr(rec.frames, key) - config.camera_delay_s
    t_force = getattr(rec.force, key)
    bad = np.zeros(len(t_force), bool) if over_capacity is None else over_capacity
    force, f_reason = interpolate_force(
        t_force[~bad],
        rec.force.force_n[~bad],
        t_frames,
        method=config.force_interpolation,
        max_gap_s=config.max_force_gap_s,
    )
    f_reason[(f_reason == 0) & _bracket_holds(t_force[~bad], t_force[bad], t_frames)] = 4
    force[f_reason > 0] = np.nan
    position, p_reason = hold_positions(
        getattr(rec.moves, key), rec.moves.offset_mm, rec.moves.is_data, t_frames
    )
    reason = np.where(f_reason > 0, f_reason, np.where(p_reason > 0, p_reason + 4, 0))
    valid = reason == 0  # force stays known (not NaN) where only the position is missing
    return FrameLabels(
        rec.frames.t_unix - config.camera_delay_s,
        force,
        position,
        valid,
        reason.astype(np.int8),
        clock,
    )


def _bracket_holds(t_good: np.ndarray, t_bad: np.ndarray, t_frames: np.ndarray) -> np.ndarray:
    """(N,) bool: a rejected reading lies between the two good readings around each frame."""
    if t_bad.size == 0 or t_good.size == 0:
        return np.zeros(len(t_frames), bool)
    t_good, t_bad = np.sort(t_good), np.sort(t_bad)
    j = np.searchsorted(t_good, t_frames, side="right")
    lo = t_good[np.clip(j - 1, 0, t_good.size - 1)]
    hi = t_good[np.clip(j, 0, t_good.size - 1)]
    return np.searchsorted(t_bad, hi, side="left") > np.searchsorted(t_bad, lo, side="right")
