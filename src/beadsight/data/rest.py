"""The rest reference of recorded frames: which frames show the pouch unloaded and settled.

A rest-referenced model (``ModelConfig.rest_input``) sees, beside its window, one image of
the pouch at rest: the average of :data:`REST_FRAMES` frames that end a run of at
least :data:`REST_SETTLE_FRAMES` valid, unloaded frames (the scale reads at most
:data:`REST_MAX_FORCE_N`). For a window ending at frame ``e`` the rest is the newest
such run ending at or before ``e``: while a press is held, the frames before it; between
presses, the pouch as it is. Training, evaluation and prediction over a dataset all pick
rest frames through :func:`rest_ends`; live sensing takes the same kind of average from
the camera (:func:`average_rest`).
"""

from __future__ import annotations

import numpy as np

from beadsight.config import REFERENCE_G_TO_N

REST_FRAMES = 8  # frames averaged into one rest image (~0.27 s at 30 fps)
REST_SETTLE_FRAMES = 15  # a rest image ends a run of at least this many unloaded frames
REST_MAX_FORCE_N = 10.0 * REFERENCE_G_TO_N  # "unloaded": the reference's no-contact level, 10 g


def rest_ends(force_n: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N,) int64: for each frame, the last frame of its rest image's :data:`REST_FRAMES`
    (the newest frame at or before it that ends :data:`REST_SETTLE_FRAMES` valid frames
    with force <= :data:`REST_MAX_FORCE_N`), or -1 where no such frame precedes it.

    force_n: (N,) N (NaN counts as loaded); valid: (N,) bool."""
    quiet = np.asarray(valid, dtype=bool) & (np.nan_to_num(force_n, nan=np.inf) <= REST_MAX_FORCE_N)
    # Length of the run of quiet frames ending at each frame.
    idx = np.arange(len(quiet))
    last_loud = np.maximum.accumulate(np.where(quiet, -1, idx))
    settled = quiet & (idx - last_loud >= max(REST_SETTLE_FRAMES, REST_FRAMES))
    return np.maximum.accumulate(np.where(settled, idx, -1)).astype(np.int64)


def rest_frame_mask(ends: np.ndarray, num_frames: int) -> np.ndarray:
    """(num_frames,) bool: the frames averaged into the rest images ending at ``ends``."""
    mask = np.zeros(num_frames, dtype=bool)
    ends = np.asarray(ends, dtype=np.int64)
    ends = ends[ends >= 0]
    for k in range(REST_FRAMES):
        mask[ends - k] = True
    return mask


def average_rest(frames: np.ndarray) -> np.ndarray:
    """(K, H, W, 3) uint8 RGB frames of the still, unloaded pouch -> (H, W, 3) uint8 RGB,
    their mean rounded to the nearest level (the rest image every path uses)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0 or frames.dtype != np.uint8:
        raise ValueError(
            f"rest frames: expected (K, H, W, 3) uint8 RGB with K >= 1, got "
            f"{frames.shape} {frames.dtype}"
        )
    return np.rint(frames.mean(axis=0, dtype=np.float32)).astype(np.uint8)


def with_rest(rest: np.ndarray, window: np.ndarray) -> np.ndarray:
    """rest (H, W, 3) and window (span, H, W, 3) uint8 -> (1 + span, H, W, 3) uint8: one
    rest-referenced model input."""
    return np.concatenate([np.asarray(rest)[None], np.asarray(window)], axis=0)
