"""The rest reference: what the sensor looks like unloaded, and what it then reads.

A :class:`RestReference` is the average of still, unloaded frames: a gray image at
:data:`REST_PX` px (for optical flow against later rest frames), the mean RGB colour
and the force the model read meanwhile (its zero-load offset). It comes from
calibration time (a rest file saved by ``beadsight health --save-rest``) or is taken
automatically the first time the pouch is certainly unloaded. :class:`RestAverage`
accumulates frames into one. Files are ``.npz`` (numpy arrays, no pickles), written
atomically.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from beadsight.errors import BeadSightError
from beadsight.files import atomic_write_bytes

REST_PX = 64  # rest images are compared at this size (px per side)
REST_FILE_VERSION = 1


@dataclass(frozen=True)
class RestReference:
    """gray: (REST_PX, REST_PX) float32 0..255; mean_rgb: (3,) float64 0..255;
    zero_force_n: mean force read at rest, N; frames: frames averaged; origin: "file",
    "auto" or "given"."""

    gray: np.ndarray
    mean_rgb: np.ndarray
    zero_force_n: float
    frames: int
    origin: str = "given"

    def save(self, path: str | Path) -> Path:
        """Write the reference to ``path`` (.npz), atomically."""
        buf = io.BytesIO()
        np.savez(
            buf,
            version=np.int64(REST_FILE_VERSION),
            gray=self.gray.astype(np.float32),
            mean_rgb=self.mean_rgb.astype(np.float64),
            zero_force_n=np.float64(self.zero_force_n),
            frames=np.int64(self.frames),
        )
        return atomic_write_bytes(path, buf.getvalue())


def load_rest(path: str | Path) -> RestReference:
    """A rest file written by :meth:`RestReference.save`; BeadSightError naming the file
    and the field that is missing or wrong."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise
    except (OSError, ValueError) as e:
        raise BeadSightError(f"rest file {path}: not a rest reference (.npz): {e}") from None
    want = {"version": (), "gray": (REST_PX, REST_PX), "mean_rgb": (3,), "zero_force_n": ()}
    for name, shape in {**want, "frames": ()}.items():
        if name not in arrays:
            raise BeadSightError(f"rest file {path}: field {name!r} is missing")
        value = arrays[name]
        if value.shape != shape or value.dtype.kind not in "fiu" or not np.isfinite(value).all():
            raise BeadSightError(
                f"rest file {path}: field {name!r} must be finite numbers of shape {shape}, "
                f"got {value.dtype} {value.shape}"
            )
    if int(arrays["version"]) != REST_FILE_VERSION:
        raise BeadSightError(
            f"rest file {path}: version {int(arrays['version'])}, expected {REST_FILE_VERSION}"
        )
    return RestReference(
        arrays["gray"].astype(np.float32),
        arrays["mean_rgb"].astype(np.float64),
        float(arrays["zero_force_n"]),
        int(arrays["frames"]),
        "file",
    )


def rest_gray(frame_rgb: np.ndarray) -> np.ndarray:
    """frame_rgb: (H, W, 3) uint8 RGB -> (REST_PX, REST_PX) float32 gray 0..255."""
    gray = cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2GRAY)
    return cv2.resize(gray, (REST_PX, REST_PX), interpolation=cv2.INTER_AREA).astype(np.float32)


class RestAverage:
    """Sums rest frames (and the force read with each) into a :class:`RestReference`."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self._gray = np.zeros((REST_PX, REST_PX), np.float64)
        self._rgb = np.zeros(3, np.float64)
        self._force = 0.0
        self.frames = 0

    def add(self, frame_rgb: np.ndarray, force_n: float) -> None:
        """frame_rgb: (H, W, 3) uint8 RGB, an unloaded still frame; force_n: its reading."""
        self._gray += rest_gray(frame_rgb)
        self._rgb += frame_rgb.reshape(-1, 3).mean(axis=0)
        self._force += float(force_n)
        self.frames += 1

    def reference(self, origin: str) -> RestReference:
        if self.frames == 0:
            raise ValueError("no rest frames yet")
        n = self.frames
        return RestReference(
            (self._gray / n).astype(np.float32), self._rgb / n, self._force / n, n, origin
        )
