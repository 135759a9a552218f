"""Bead motion between two rest states: dense optical flow on their gray images.

Rest states are compared as gray images of :data:`REST_PX` px (:func:`rest_gray`), each
normalised to a fixed contrast (a brightness change is not motion), by OpenCV's Farneback
flow. :func:`bead_motion` splits the flow (the border :data:`FLOW_MARGIN_PX` left out) into

* ``shift``: its median: the whole image moved (the camera against the pouch), mm;
* ``deformation``: its affine part without translation (a least-squares fit), as mm of
  displacement at half the field of view: the beads creeping as a whole;
* ``local_mm``: the largest motion the affine fit does not explain, averaged over
  :data:`LOCAL_PX` x :data:`LOCAL_PX` px (about 4.5 mm of the pouch), away from the border
  by :data:`LOCAL_MARGIN_PX` (where a drift's warp brings in what was outside the image):
  beads pushed aside at one place, as a finger does.

The health monitor judges drift by the first two (:mod:`beadsight.health.monitor`); the
rest tracker refuses a rest state that moved locally with no load read, a slow load
(:mod:`beadsight.health.rest`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

REST_PX = 64  # rest states are compared at this size (px per side)
FLOW_MARGIN_PX = 4  # flow this close to the image border is left out (px at REST_PX)
LOCAL_PX = 7  # local motion is averaged over blocks of this many px per side
LOCAL_MARGIN_PX = 8  # ... and looked for this far from the border (px at REST_PX)
_FLOW_CONTRAST = 40.0  # images are normalised to this standard deviation before flow


def rest_gray(image_rgb: np.ndarray) -> np.ndarray:
    """image_rgb: (H, W, 3) uint8 RGB -> (REST_PX, REST_PX) float32 gray 0..255."""
    gray = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(gray, (REST_PX, REST_PX), interpolation=cv2.INTER_AREA).astype(np.float32)


def _basis() -> np.ndarray:
    """(P, 3): x, y (px from the image centre) and 1 of each pixel inside the margin."""
    m, n = FLOW_MARGIN_PX, REST_PX
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64) - (n - 1) / 2
    basis = np.stack([cols, rows, np.ones_like(cols)], axis=-1)
    return basis[m:-m, m:-m].reshape(-1, 3)


_BASIS = _basis()


def _normalised(gray: np.ndarray) -> np.ndarray:
    """Zero-mean, fixed-contrast uint8 (optical flow then ignores brightness changes)."""
    g = gray.astype(np.float32)
    g = (g - g.mean()) * (_FLOW_CONTRAST / max(float(g.std()), 1e-3)) + 128.0
    return np.clip(g, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Motion:
    """The motion between two rest states (module docstring)."""

    deformation: np.ndarray  # (2, 2) mm of displacement per half field of view
    shift: np.ndarray  # (2,) mm
    local_mm: float


def bead_motion(before: np.ndarray, after: np.ndarray, sensor_size_mm: float) -> Motion:
    """The motion from gray image ``before`` to ``after`` (:func:`rest_gray` images) of a
    field of view ``sensor_size_mm`` mm wide."""
    flow = cv2.calcOpticalFlowFarneback(
        _normalised(before), _normalised(after), None, 0.5, 3, 15, 3, 5, 1.1, 0
    )  # (REST_PX, REST_PX, 2) px, before -> after
    m = FLOW_MARGIN_PX
    inner = flow[m:-m, m:-m]
    vectors = inner.reshape(-1, 2).astype(np.float64)
    coef, *_ = np.linalg.lstsq(_BASIS, vectors, rcond=None)  # (3, 2): d(flow)/dx, /dy, offset
    mm_per_px = sensor_size_mm / REST_PX
    residual = (vectors - _BASIS @ coef).reshape(inner.shape).astype(np.float32)
    local = cv2.blur(np.hypot(residual[..., 0], residual[..., 1]), (LOCAL_PX, LOCAL_PX))
    inside = LOCAL_MARGIN_PX - FLOW_MARGIN_PX
    local = local[inside:-inside, inside:-inside]
    return Motion(
        deformation=coef[:2].T * (REST_PX / 2) * mm_per_px,
        shift=np.median(vectors, axis=0) * mm_per_px,
        local_mm=float(local.max()) * mm_per_px,
    )
