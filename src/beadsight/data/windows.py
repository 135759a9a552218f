"""Model inputs read from a dataset: the window of ``span`` frames ending at a frame, oldest
first, and for a rest-referenced model its rest image in front (``(inputs, S, S, 3)``).

The one builder of dataset inputs: training reads through it (host mode:
:func:`read_window`; the device mode gathers the same frames on the device and averages
them the same way) and so do evaluation, calibration and ``predict`` on a dataset
(:class:`WindowReader`, :class:`RestImages`). Frames are resized to the model's size by
area averaging (``cv2.INTER_AREA``) before anything else, so a rest image is the average
(:func:`~beadsight.data.rest.average_rest`) of its :data:`~beadsight.data.rest.REST_FRAMES`
resized frames, the last of them given by :func:`~beadsight.data.rest.rest_ends`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from beadsight.data.rest import (
    REST_FRAMES,
    REST_MAX_FORCE_N,
    REST_SETTLE_FRAMES,
    average_rest,
    rest_ends,
    with_rest,
)

if TYPE_CHECKING:
    from beadsight.data.dataset import Dataset

STATS_MAX_FRAMES = 512  # frames sampled for the pixel mean/std


def resize_frames(frames: np.ndarray, size: int) -> np.ndarray:
    """(n, S, S, 3) uint8 -> (n, size, size, 3) uint8 by area averaging (cv2.INTER_AREA)."""
    if frames.shape[1] == size and frames.shape[2] == size:
        return frames
    out = np.empty((len(frames), size, size, 3), dtype=np.uint8)
    for i, frame in enumerate(frames):
        out[i] = cv2.resize(frame, (size, size), interpolation=cv2.INTER_AREA)
    return out


def rest_image(ds: Dataset, rest_end: int, image_size: int) -> np.ndarray:
    """(image_size, image_size, 3) uint8 RGB: the rest image whose last frame is ``rest_end``
    (the average of the :data:`REST_FRAMES` frames ending there, each resized first)."""
    frames = ds.read_frames(rest_end - REST_FRAMES + 1, rest_end + 1)
    return average_rest(resize_frames(frames, image_size))


def read_window(
    ds: Dataset, end: int, span: int, image_size: int, rest_end: int | None = None
) -> np.ndarray:
    """The input ending at frame ``end``: (span, S, S, 3) uint8 RGB frames oldest first, or
    with ``rest_end`` (the last frame of its rest image) (1 + span, S, S, 3), the rest image
    first. S is ``image_size``. One contiguous read: for random access (training)."""
    window = resize_frames(ds.read_frames(end - span + 1, end + 1), image_size)
    if rest_end is None:
        return window
    return with_rest(rest_image(ds, rest_end, image_size), window)


class RestImages:
    """The rest image of each frame of a dataset, by :func:`rest_ends` (the newest run of
    :data:`REST_SETTLE_FRAMES` valid unloaded frames at or before it), at ``image_size``.

    Neighbouring frames share a rest image: those of the last call are kept, not read again.
    """

    def __init__(self, ds: Dataset, image_size: int | None = None):
        self.ds = ds
        self.image_size = image_size or ds.image_size
        self.ends = rest_ends(ds.force_n, ds.valid)  # (N,) int64, -1: no rest image
        self._kept: dict[int, np.ndarray] = {}

    def has_rest(self, frames: np.ndarray) -> np.ndarray:
        """(B,) frame indices -> (B,) bool: the frame has a rest image before it."""
        return self.ends[np.asarray(frames, dtype=np.int64)] >= 0

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        """(B,) frame indices -> (B, S, S, 3) uint8 RGB rest images. ValueError naming the
        first frame that has none."""
        frames = np.asarray(frames, dtype=np.int64)
        ends = self.ends[frames]
        if (ends < 0).any():
            raise ValueError(
                f"{self.ds.path}: frame {int(frames[np.argmax(ends < 0)])} has no rest image "
                f"before it (a run of {REST_SETTLE_FRAMES} valid frames at most "
                f"{REST_MAX_FORCE_N:.3f} N)"
            )
        kept = {}
        for r in np.unique(ends).tolist():
            image = self._kept.get(r)
            kept[r] = rest_image(self.ds, r, self.image_size) if image is None else image
        self._kept = kept
        out = np.empty((len(frames), self.image_size, self.image_size, 3), dtype=np.uint8)
        for k, r in enumerate(ends.tolist()):
            out[k] = kept[r]
        return out


class WindowReader:
    """Reads model inputs for batches of end frames in increasing order.

    ``reader(ends)``: (B,) end indices -> (B, inputs, S, S, 3) uint8 RGB: with ``rest`` the
    rest image first (:class:`RestImages`), then the ``span`` frames oldest first; S is
    ``image_size`` (the dataset's if None; frames are resized with INTER_AREA). The frames
    a batch shares with the previous one (the last ``span - 1``) are reused instead of read
    again; each contiguous run of the rest is read once.
    """

    def __init__(self, ds: Dataset, span: int, image_size: int | None = None, rest: bool = False):
        self.ds = ds
        self.span = span
        self.image_size = image_size or ds.image_size
        self.rests = RestImages(ds, self.image_size) if rest else None
        self._offsets = np.arange(span - 1, -1, -1, dtype=np.int64)
        self._index = np.zeros(0, dtype=np.int64)  # sorted frame indices held in _frames
        self._frames = np.zeros((0, self.image_size, self.image_size, 3), dtype=np.uint8)

    def _read(self, start: int, stop: int) -> np.ndarray:
        return resize_frames(self.ds.read_frames(start, stop), self.image_size)

    def __call__(self, ends: np.ndarray) -> np.ndarray:
        ends = np.asarray(ends, dtype=np.int64)
        wanted = ends[:, None] - self._offsets[None]  # (B, span)
        need = np.unique(wanted)
        if need.size and (need[0] < 0 or need[-1] >= len(self.ds)):
            raise IndexError(
                f"windows need frames {need[0]}..{need[-1]}; {self.ds.path} has {len(self.ds)}"
            )
        rest = None if self.rests is None else self.rests(ends)  # (B, S, S, 3)
        block = np.empty((need.size, *self._frames.shape[1:]), dtype=np.uint8)
        have = np.isin(need, self._index)
        block[have] = self._frames[np.searchsorted(self._index, need[have])]
        missing = need[~have]
        if missing.size:
            runs = np.split(missing, np.flatnonzero(np.diff(missing) != 1) + 1)
            block[~have] = np.concatenate([self._read(int(r[0]), int(r[-1]) + 1) for r in runs])
        keep = max(need.size - (self.span - 1), 0)
        self._index, self._frames = need[keep:], block[keep:].copy()
        windows = block[np.searchsorted(need, wanted)]  # (B, span, S, S, 3)
        if rest is None:
            return windows
        return np.concatenate([rest[:, None], windows], axis=1)  # (B, 1 + span, S, S, 3)


def read_windows(
    ds: Dataset, ends: np.ndarray, span: int, image_size: int | None = None, rest: bool = False
) -> np.ndarray:
    """:class:`WindowReader` in one call: (B,) end indices -> (B, inputs, S, S, 3) uint8 RGB."""
    return WindowReader(ds, span, image_size, rest)(ends)


def pixel_stats(
    ds: Dataset, frame_mask: np.ndarray, image_size: int, max_frames: int = STATS_MAX_FRAMES
) -> tuple[list[float], list[float]]:
    """Per-channel RGB mean and std (0..255 units) of up to ``max_frames`` frames in ``frame_mask``,
    evenly spaced, measured at the training ``image_size`` (what the network sees)."""
    idx = np.flatnonzero(frame_mask)
    if len(idx) == 0:
        raise ValueError(f"{ds.path}: no frames to measure pixel statistics on")
    idx = idx[np.unique(np.linspace(0, len(idx) - 1, min(len(idx), max_frames)).astype(np.int64))]
    total = np.zeros(3)
    total_sq = np.zeros(3)
    count = 0
    for i in range(0, len(idx), 64):
        block = resize_frames(ds.read_frames_at(idx[i : i + 64]), image_size)
        pixels = block.reshape(-1, 3).astype(np.float64)
        total += pixels.sum(0)
        total_sq += (pixels * pixels).sum(0)
        count += len(pixels)
    mean = total / count
    std = np.sqrt(np.maximum(total_sq / count - mean**2, 0.0))
    return mean.tolist(), np.maximum(std, 1e-3).tolist()


# --- streams (a video, a live or simulated session): frames in order, no dataset -----
class WindowBuffer:
    """The last ``span - 1`` frames, so a stream of chunks becomes model windows.

    push(frames (n, S, S, 3)) -> windows (m, span, S, S, 3) for the last m = n - k
    frames of the chunk, where the first k frames of the whole stream (k < span)
    lack a full window. Memory: span - 1 frames plus one chunk.
    """

    def __init__(self, span: int):
        self.span = span
        self.seen = 0
        self._tail: np.ndarray | None = None

    def push(self, frames: np.ndarray) -> tuple[np.ndarray, int]:
        """Returns (windows, first): windows end at chunk frames ``first .. n-1``."""
        t = self.span
        full = frames if self._tail is None else np.concatenate([self._tail, frames])
        n_prev = len(full) - len(frames)
        first = min(max(t - 1 - self.seen, 0), len(frames))
        self.seen += len(frames)
        self._tail = full[max(len(full) - (t - 1), 0) :].copy() if t > 1 else full[:0].copy()
        if first == len(frames):
            return np.zeros((0, t, *frames.shape[1:]), frames.dtype), first
        view = np.lib.stride_tricks.sliding_window_view(full, t, axis=0)  # (m, S, S, 3, T)
        start = n_prev + first - (t - 1)
        return np.moveaxis(view[start:], -1, 1), first


def stream_windows(
    frames: np.ndarray, ends: np.ndarray, span: int, rest: np.ndarray | None = None
) -> np.ndarray:
    """Model inputs ending at ``ends`` of a stream held in memory.

    frames: (N, S, S, 3) uint8 RGB, in order; ends: (B,) indices, each >= span - 1;
    rest: an (S, S, 3) uint8 RGB rest image put in front of every window, or (B, S, S, 3):
    one per window.
    returns: (B, inputs, S, S, 3) uint8 RGB (a copy), windows oldest first.
    """
    ends = np.asarray(ends, dtype=np.int64)
    if ends.size and (ends.min() < span - 1 or ends.max() >= len(frames)):
        raise IndexError(
            f"windows of {span} frames need ends in {span - 1}..{len(frames) - 1}, "
            f"got {int(ends.min())}..{int(ends.max())}"
        )
    view = np.lib.stride_tricks.sliding_window_view(frames, span, axis=0)  # (N-span+1,S,S,3,span)
    windows = np.moveaxis(view[ends - (span - 1)], -1, 1)  # (B, span, S, S, 3)
    if rest is None:
        return np.ascontiguousarray(windows)
    rest = np.asarray(rest)
    rest = rest[:, None] if rest.ndim == 4 else rest[None, None]
    return np.concatenate([np.broadcast_to(rest, (len(ends), 1, *rest.shape[2:])), windows], axis=1)
