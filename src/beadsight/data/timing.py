"""What a dataset's timestamps can tell: duration, and where the frame sequence breaks.

The reference stores unix time as float32, whose spacing near 1.7e9 s is 128 s:
those timestamps say nothing about frame order or gaps, so durations come from the
frame count and the frame rate instead, with a warning. Fine (float64) timestamps
also show where frames were dropped: a window of consecutive dataset rows across
such a gap is not a real history.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from beadsight.data.dataset import Dataset

GAP_FRAMES = 1.5  # consecutive frames further apart than this many frame periods: a gap


def timestamp_resolution_s(t: np.ndarray) -> float:
    """Spacing of the stored timestamps near their largest value (s).

    Values that are all exactly float32 numbers are taken as float32 (the reference's
    time field): 128 s at today's unix times. 0.0 when there are no finite values.
    """
    t = np.asarray(t, np.float64)
    t = t[np.isfinite(t)]
    if t.size == 0:
        return 0.0
    largest = float(np.abs(t).max())
    if np.array_equal(t.astype(np.float32).astype(np.float64), t):
        return float(np.spacing(np.float32(largest)))
    return float(np.spacing(largest))


def timestamps_are_coarse(t: np.ndarray, fps: float) -> bool:
    """Whether the timestamps cannot resolve one frame period."""
    return timestamp_resolution_s(t) > 1.0 / fps


def duration(ds: Dataset) -> dict[str, Any]:
    """duration_s, how it was found (duration_from) and a warning (None when all is well)."""
    n, t, fps = len(ds), ds.timestamp_s, ds.fps
    if n == 0:
        return {"duration_s": 0.0, "duration_from": "empty", "warning": None}
    resolution = timestamp_resolution_s(t)
    if resolution > 1.0 / fps:
        return {
            "duration_s": n / fps,
            "duration_from": "frame count / fps",
            "warning": (
                f"{ds.path}: the time field cannot resolve frames: its values are float32, "
                f"spaced {resolution:g} s apart near {float(np.nanmax(np.abs(t))):.4g} s, "
                f"coarser than the {1000.0 / fps:.1f} ms frame period; duration_s is the frame "
                f"count / fps ({n} / {fps:g})"
            ),
        }
    return {"duration_s": float(t[-1] - t[0]), "duration_from": "timestamps", "warning": None}


def frame_breaks(timestamp_s: np.ndarray, fps: float) -> np.ndarray:
    """(N,) bool: frame ``i`` does not directly follow frame ``i - 1`` (time going backwards,
    standing still, or a gap of more than GAP_FRAMES periods). All False when the
    timestamps are too coarse to tell (the reference's float32 time)."""
    t = np.asarray(timestamp_s, np.float64)
    breaks = np.zeros(len(t), bool)
    if len(t) < 2 or timestamps_are_coarse(t, fps):
        return breaks
    dt = np.diff(t)
    breaks[1:] = ~((dt > 0) & (dt <= GAP_FRAMES / fps))
    return breaks
