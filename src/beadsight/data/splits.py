"""Train/val/test splits by press, and the frames that can end a causal window.

Splitting by press (not by frame) keeps the frames of one press together, so a
model is never tested on frames of a press it trained on. Both training and
evaluation select samples through :func:`window_ends`, so they agree exactly.
"""

from __future__ import annotations

import numpy as np

from beadsight.config import DEFAULT_SPLIT_FRACTIONS as DEFAULT_FRACTIONS

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
    press_id: np.ndarray, valid: np.ndarray, window: int, presses: np.ndarray | None = None
) -> np.ndarray:
    """Indices of frames that can end a window of ``window`` consecutive frames.

    press_id: (N,) int press cycle of each frame; valid: (N,) bool.
    presses: optional (K,) press ids to keep (e.g. one split's ids).
    A frame ``i`` qualifies when frames ``i-window+1 .. i`` are all valid and all in
    the same press cycle. returns: (M,) int64 sorted.
    """
    press_id = np.asarray(press_id)
    valid = np.asarray(valid, dtype=bool)
    n = len(press_id)
    if n < window:
        return np.zeros(0, dtype=np.int64)
    ok = valid & (press_id >= 0)
    new_cycle = np.ones(n, dtype=bool)
    new_cycle[1:] = press_id[1:] != press_id[:-1]
    # Length of the run of good frames of one press cycle ending at each frame.
    run = np.zeros(n, dtype=np.int64)
    count = 0
    for i, (good, fresh) in enumerate(zip(ok.tolist(), new_cycle.tolist(), strict=True)):
        count = 0 if not good else (1 if fresh else count + 1)
        run[i] = count
    ends = np.flatnonzero(run >= window)
    if presses is not None:
        ends = ends[np.isin(press_id[ends], np.asarray(presses))]
    return ends.astype(np.int64)
