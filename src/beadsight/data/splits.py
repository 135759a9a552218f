"""Train/val/test splits by press, and the frames that can end a causal window.

Splitting by press (not by frame) keeps the frames of one press together, so a
model is never tested on frames of a press it trained on. Both training and
evaluation select samples through :func:`dataset_window_ends`, so they agree
exactly: every frame with a full window of valid, continuous history, also when
that history reaches into the previous press.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from beadsight.config import DEFAULT_SPLIT_FRACTIONS as DEFAULT_FRACTIONS
from beadsight.data.rest import rest_ends
from beadsight.data.timing import frame_breaks

if TYPE_CHECKING:
    from beadsight.data.dataset import Dataset

SPLITS = ("train", "val", "test")


def split_presses(
    num_presses: int, fractions: tuple[float, float, float] = DEFAULT_FRACTIONS, seed: int = 0
) -> dict[str, np.ndarray]:
    """Shuffle press ids with ``seed`` and cut them by ``fractions`` (train, val, test).

    returns: {"train": ids, "val": ids, "test": ids}, each sorted int64. With at
    least 3 presses every split gets at least one.
    """
    if len(fractions) != 3 or min(fractions) < 0 or not np.isclose(sum(fractions), 1.0):
        raise ValueError(
            f"split fractions must be three non-negative numbers summing to 1, got {fractions}"
        )
    if num_presses < 1:
        raise ValueError("cannot split a dataset with no presses")
    ids = np.random.default_rng(seed).permutation(num_presses)
    n_val = int(round(fractions[1] * num_presses))
    n_test = int(round(fractions[2] * num_presses))
    if num_presses >= 3:
        n_val = max(n_val, 1) if fractions[1] > 0 else 0
        n_test = max(n_test, 1) if fractions[2] > 0 else 0
    n_train = num_presses - n_val - n_test
    return {
        "train": np.sort(ids[:n_train]),
        "val": np.sort(ids[n_train : n_train + n_val]),
        "test": np.sort(ids[n_train + n_val :]),
    }


def window_ends(
    press_id: np.ndarray,
    valid: np.ndarray,
    span: int,
    presses: np.ndarray | None = None,
    breaks: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of frames that end a window of ``span`` consecutive frames of real history.

    press_id: (N,) int press cycle of each frame; valid: (N,) bool; breaks: optional (N,)
    bool, frame ``i`` does not directly follow frame ``i - 1`` (dropped frames; see
    :func:`beadsight.data.timing.frame_breaks`). presses: optional (K,) press ids to
    keep (e.g. one split's ids).

    A frame ``i`` qualifies when it belongs to a press cycle and frames
    ``i-span+1 .. i`` are all valid with no break after the first: the recording is
    continuous, so the window may reach back into the previous press's frames. A
    frame belongs to its own press's split whatever its window covers.
    returns: (M,) int64 sorted.
    """
    press_id = np.asarray(press_id)
    valid = np.asarray(valid, dtype=bool)
    n = len(press_id)
    if n < span:
        return np.zeros(0, dtype=np.int64)
    fresh = np.zeros(n, bool) if breaks is None else np.asarray(breaks, bool)
    # Length of the run of valid, unbroken frames ending at each frame.
    run = np.zeros(n, dtype=np.int64)
    count = 0
    for i, (good, brk) in enumerate(zip(valid.tolist(), fresh.tolist(), strict=True)):
        count = 0 if not good else (1 if brk else count + 1)
        run[i] = count
    ends = np.flatnonzero((run >= span) & (press_id >= 0))
    if presses is not None:
        ends = ends[np.isin(press_id[ends], np.asarray(presses))]
    return ends.astype(np.int64)


def dataset_window_ends(
    ds: Dataset, span: int, presses: np.ndarray | None = None, rest: bool = False
) -> np.ndarray:
    """:func:`window_ends` of dataset ``ds``, broken where its timestamps show dropped frames.
    rest: only windows with a rest image before them (:func:`beadsight.data.rest.rest_ends`),
    as a rest-referenced model needs.

    Training and evaluation select their frames through this one function."""
    breaks = frame_breaks(ds.timestamp_s, ds.fps)
    ends = window_ends(ds.press_id, ds.valid, span, presses, breaks)
    if rest:
        ends = ends[rest_ends(ds.force_n, ds.valid)[ends] >= 0]
    return ends


def valid_frames(ds: Dataset, presses: np.ndarray | None = None) -> np.ndarray:
    """(M,) int64 indices of the valid frames of the press cycles ``presses`` (all if None):
    what an evaluation could cover at best (``coverage`` = evaluated / these)."""
    keep = ds.valid & (ds.press_id >= 0)
    if presses is not None:
        keep &= np.isin(ds.press_id, np.asarray(presses))
    return np.flatnonzero(keep).astype(np.int64)
