"""The fixed pressure colour scale of every output that draws the map (the viewer's PNG,
Foxglove's ``pressure_image``): one colour map, one rule from kPa to colour."""

from __future__ import annotations

import cv2
import numpy as np

COLORMAP = cv2.COLORMAP_INFERNO


def colormap_bgr(levels: int = 256) -> np.ndarray:
    """(levels, 3) uint8 BGR colours of the fixed pressure scale (0 kPa first)."""
    ramp = np.arange(levels, dtype=np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(ramp, COLORMAP).reshape(levels, 3)


def colour_indices(pressure_kpa: np.ndarray, max_kpa: float, levels: int) -> np.ndarray:
    """(H, W) kPa -> (H, W) uint8 indices into a ``levels``-entry colour map on the fixed
    scale 0..max_kpa (NaN reads as 0, values above ``max_kpa`` saturate)."""
    top = levels - 1
    return np.clip(np.nan_to_num(pressure_kpa) * (top / max_kpa), 0, top).astype(np.uint8)
