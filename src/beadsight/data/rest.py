"""The rest reference of recorded frames: which frames show the pouch unloaded and settled.

A rest-referenced model (``ModelConfig.rest_input``) sees, beside its window, one image of
the pouch at rest: the average of :data:`REST_FRAMES` frames that end a run of at
least :data:`REST_SETTLE_FRAMES` valid, unloaded frames (the scale reads at most
:data:`REST_MAX_FORCE_N`). For a window ending at frame ``e`` the rest is the newest
such run ending at or before ``e``: while a press is held, the frames before it; between
presses, the pouch as it is. Training, evaluation and prediction over a dataset all pick
rest frames through :func:`rest_ends`; live sensing takes the same kind of average from
the camera (:func:`average_rest`).

The rest file
-------------
A :class:`RestReference` (the rest image, how many frames made it, when) is stored as an
``.npz`` file, the one format of ``beadsight live --rest``, ``beadsight health --rest``
/ ``--save-rest`` and ``beadsight calibrate --rest``: arrays ``version`` (int64, 2),
``image`` ((S, S, 3) uint8 RGB, S <= :data:`REST_FILE_MAX_PX`), ``frames`` (int64) and
``taken_at_s`` (float64, unix s; NaN if unknown). :func:`load_rest_file` checks each
array's declared dtype, shape and size before reading it
(:func:`beadsight.safe_numpy.read_npz`): a small file cannot make it allocate more
than the image's few MB, whatever its headers claim.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beadsight.config import REFERENCE_G_TO_N
from beadsight.errors import BeadSightError
from beadsight.files import atomic_write_bytes
from beadsight.safe_numpy import UnsafeContent, read_npz

REST_FRAMES = 8  # frames averaged into one rest image (~0.27 s at 30 fps)
REST_SETTLE_FRAMES = 15  # a rest image ends a run of at least this many unloaded frames
REST_MAX_FORCE_N = 10.0 * REFERENCE_G_TO_N  # "unloaded": the reference's no-contact level, 10 g
REST_FILE_VERSION = 2  # 1 (beadsight <= 0.1 health files: a 64 px gray image) is not read
REST_FILE_MAX_PX = 1024  # the largest rest image a rest file may hold (3 MiB of RGB)
REST_ORIGINS = ("start-up", "refreshed", "requested", "file", "given")


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


class RestFileError(BeadSightError):
    """A rest file that cannot be used: not one, damaged, forged, or the wrong size."""


@dataclass(frozen=True)
class RestReference:
    """The pouch at rest: image (S, S, 3) uint8 RGB, the average of ``frames`` still,
    unloaded frames (:func:`average_rest`); taken_at_s: when (frame time, s; NaN if
    unknown); origin: one of :data:`REST_ORIGINS` ("start-up": taken when sensing
    started, "refreshed": taken later, "requested": taken when the user asked (the pouch
    said to be unloaded), "file": loaded from a rest file, "given": made by the caller)."""

    image: np.ndarray
    frames: int = 1
    taken_at_s: float = math.nan
    origin: str = "given"

    def __post_init__(self) -> None:
        image = np.asarray(self.image)
        if image.ndim != 3 or image.shape[-1] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"rest image: expected (S, S, 3) uint8 RGB, got {image.shape} {image.dtype}"
            )
        if self.origin not in REST_ORIGINS:
            raise ValueError(f"rest origin must be one of {REST_ORIGINS}, got {self.origin!r}")

    @property
    def image_size(self) -> int:
        return int(self.image.shape[0])

    def save(self, path: str | Path) -> Path:
        """Write the rest file ``path`` (.npz), atomically."""
        buf = io.BytesIO()
        np.savez(
            buf,
            version=np.int64(REST_FILE_VERSION),
            image=np.ascontiguousarray(self.image, dtype=np.uint8),
            frames=np.int64(self.frames),
            taken_at_s=np.float64(self.taken_at_s),
        )
        return atomic_write_bytes(path, buf.getvalue())


def load_rest_file(path: str | Path, image_size: int | None = None) -> RestReference:
    """The rest file ``path`` (module docstring) as a :class:`RestReference` (origin
    "file"). image_size: the model's frame size the image must have (None: any square
    size up to :data:`REST_FILE_MAX_PX`). Raises :class:`RestFileError` naming the file
    and what is wrong; FileNotFoundError if it does not exist."""
    path = Path(path)
    if path.is_dir():
        raise RestFileError(f"rest file {path}: is a folder; expected a rest file (.npz)")
    most = REST_FILE_MAX_PX * REST_FILE_MAX_PX * 3
    fields = {
        "version": ((), "iu"),
        "image": ((None, None, 3), "u"),
        "frames": ((), "iu"),
        "taken_at_s": ((), "f"),
    }
    try:
        arrays = read_npz(path, fields, max_bytes=most)
    except UnsafeContent as e:
        raise RestFileError(f"rest file {path}: {e}") from None
    version = int(arrays["version"])
    if version != REST_FILE_VERSION:
        raise RestFileError(
            f"rest file {path}: version {version}, expected {REST_FILE_VERSION} (save the rest "
            "again with beadsight health --save-rest)"
        )
    image, frames = arrays["image"], int(arrays["frames"])
    if image.shape[0] != image.shape[1] or image.shape[0] < 1:
        raise RestFileError(
            f"rest file {path}: the image is {image.shape[1]}x{image.shape[0]} px; expected a square"
        )
    if image_size is not None and image.shape[0] != image_size:
        raise RestFileError(
            f"rest file {path}: the image is {image.shape[0]}x{image.shape[0]} px but the "
            f"model expects {image_size}x{image_size} (take the rest with this model's frames)"
        )
    if frames < 1:
        raise RestFileError(f"rest file {path}: frames must be >= 1, got {frames}")
    return RestReference(image, frames, float(arrays["taken_at_s"]), "file")
