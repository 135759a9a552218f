"""Press segmentation from a force trace, with contact hysteresis.

A press is a run of consecutive valid frames in contact at one position. Contact
begins when force reaches ``contact_n`` and ends when it falls to ``release_n``
(hysteresis: values in between keep the previous state), so slow loading and
unloading ramps that hover between the thresholds do not chatter. A press still
in contact at the end of the recording is kept.

Every frame is then assigned to one press cycle (for splitting by press): the
frames between two presses are divided at the midpoint, so approach and retreat
frames travel with their press.
"""

from __future__ import annotations

import numpy as np

from beadsight.config import ContactThresholds

POSITION_TOLERANCE_MM = 0.5  # a commanded move larger than this starts a new press


def contact_state(
    force_n: np.ndarray, valid: np.ndarray, thresholds: ContactThresholds
) -> np.ndarray:
    """(N,) newtons, (N,) bool -> (N,) bool contact with hysteresis; invalid frames break contact."""
    force = np.asarray(force_n, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    contact = np.zeros(len(force), dtype=bool)
    state = False
    # A Python loop over the hysteresis state machine: ~1 us/frame, fine for 10^6 frames.
    for i, (f, ok) in enumerate(zip(force.tolist(), valid.tolist(), strict=True)):
        if not ok or f != f:  # invalid or NaN
            state = False
        elif state and f <= thresholds.release_n:
            state = False
        elif not state and f >= thresholds.contact_n:
            state = True
        contact[i] = state
    return contact


def segment_presses(
    force_n: np.ndarray,
    valid: np.ndarray,
    position_mm: np.ndarray | None = None,
    thresholds: ContactThresholds = ContactThresholds(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find presses.

    force_n: (N,) newtons; valid: (N,) bool; position_mm: (N, 2) or None.
    returns: ``contact`` (N,) bool; ``press_id`` (N,) int32, the press cycle of every
    frame (-1 for all frames if there is no press); ``presses`` (P, 2) int64
    ``[start, stop)`` frame ranges of each press's contact.
    """
    contact = contact_state(force_n, valid, thresholds)
    n = len(contact)
    edges = np.diff(np.concatenate([[0], contact.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    stops = np.flatnonzero(edges == -1)
    runs = list(zip(starts.tolist(), stops.tolist(), strict=True))
    if position_mm is not None and runs:
        runs = _split_at_moves(runs, np.asarray(position_mm, dtype=np.float64))
    presses = np.asarray(runs, dtype=np.int64).reshape(-1, 2)
    press_id = np.full(n, -1, dtype=np.int32)
    if len(presses):
        # Boundaries between cycles: midpoints of the gaps between consecutive presses.
        bounds = (presses[1:, 0] + presses[:-1, 1]) // 2
        press_id[:] = np.searchsorted(bounds, np.arange(n), side="right")
    return contact, press_id, presses


def _split_at_moves(runs: list[tuple[int, int]], position: np.ndarray) -> list[tuple[int, int]]:
    out = []
    for start, stop in runs:
        seg = position[start:stop]
        jumps = np.flatnonzero(np.linalg.norm(np.diff(seg, axis=0), axis=1) > POSITION_TOLERANCE_MM)
        cuts = [start, *(start + j + 1 for j in jumps.tolist()), stop]
        out += [(a, b) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]
    return out
