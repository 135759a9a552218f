"""Raw camera frames: the sensor-space view warped back into a 1280x1024 fisheye image.

The reference preprocessing (reference-facts section 2, :mod:`beadsight.preprocess`)
maps a raw frame to sensor space: centre square crop, "defisheye" remap
(``r_s = ifoc * atan(r_d / ofoc)``), crop 750 x 750, resize. This module inverts
that chain pixel by pixel, so a raw frame rendered here comes back, through the
reference preprocessing, as (approximately: resampled twice) the sensor-space
image. For every raw pixel centre:

1. position in the centre square relative to its centre ``c = (side - 1) // 2``.
   The reference samples by truncation, so raw pixel ``p`` stands for the
   continuous source coordinate ``p + 0.5``;
2. ``r_d = ofoc * tan(r_s / ifoc)`` (the inverse of the defisheye radius law),
   giving the unwarped pixel ``c + d * r_d / r_s``;
3. minus the crop origin; the crop's 750 pixels span the sensor's 41 mm, so the
   fraction across the crop is the fraction across the sensor-space image.

Raw pixels outside the sensor's field of view show a static view of the housing
(dark, with the LEDs' glare), and everything beyond the lens's 180 degree image
circle is black. Sensor noise is added at raw resolution, then optional MJPG
(JPEG) compression, as a USB camera delivers it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from beadsight.preprocess import (
    REFERENCE_INPUT_HW,
    reference_crop,
    reference_focal_lengths,
    reference_square,
)
from beadsight.sim.config import SimConfig
from beadsight.sim.optics.render import jpeg_roundtrip, noise_tiles

RAW_HW = REFERENCE_INPUT_HW  # (rows, cols) of a raw camera frame
_EDGE_MARGIN = 2.0  # raw pixels this far (in crop pixels) beyond the field still show it
_OUTSIDE = -1.0e4  # map value for raw pixels that do not see the sensor
HOUSING_LEVEL = 12.0  # the printed housing around the window, 0..255
HOUSING_GLOW = 26.0  # light from the pouch spilling onto the housing near the window
HOUSING_GLOW_PX = 90.0  # decay length of that glow in raw pixels
_NOISE_PAD = 64


def raw_to_sensor_maps(
    sensor_px: int, input_hw: tuple[int, int] = RAW_HW
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each raw pixel looks in a ``sensor_px`` sensor-space image.

    returns: ``(map_rows, map_cols, inside)``: (H, W) float32 sensor-space pixel
    coordinates (pixel ``i`` centred at ``i``, as ``cv2.remap`` wants; ``-1e4``
    for raw pixels that do not see the sensor), and (H, W) bool, True where the
    raw pixel sees the sensor's field of view.
    """
    h, w = input_hw
    row0, col0, side = reference_square(input_hw)
    centre = (side - 1) // 2
    ofoc, ifoc = reference_focal_lengths(side)
    crop_r0, crop_c0, crop_n = reference_crop(side)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    sy = v - row0 + 0.5 - centre  # truncation: raw pixel p stands for p + 0.5
    sx = u - col0 + 0.5 - centre
    r_s = np.hypot(sy, sx)
    angle = r_s / ifoc
    seen = angle < math.pi / 2 * 0.999  # inside the 180 degree image circle
    r_d = ofoc * np.tan(np.where(seen, angle, 0.0))
    scale = np.divide(r_d, r_s, out=np.ones_like(r_s), where=r_s > 1e-9)
    a = centre + sy * scale  # unwarped square's pixel index (centred at integers)
    b = centre + sx * scale
    frac_r = (a - crop_r0 + 0.5) / crop_n  # 0..1 across the crop == across the sensor
    frac_c = (b - crop_c0 + 0.5) / crop_n
    margin = _EDGE_MARGIN / crop_n
    inside = (
        seen
        & (frac_r > -margin)
        & (frac_r < 1 + margin)
        & (frac_c > -margin)
        & (frac_c < 1 + margin)
    )
    map_rows = np.clip(frac_r * sensor_px - 0.5, 0, sensor_px - 1)
    map_cols = np.clip(frac_c * sensor_px - 0.5, 0, sensor_px - 1)
    map_rows = np.where(inside, map_rows, _OUTSIDE).astype(np.float32)
    map_cols = np.where(inside, map_cols, _OUTSIDE).astype(np.float32)
    return map_rows, map_cols, inside


class RawCamera:
    """Warp sensor-space radiance images into raw 1280x1024 BGR fisheye frames.

    sensor_px: resolution of the sensor-space images it is given (the raw frame
    resolves ~680 px across the sensor, so 768 keeps it sharp).
    """

    def __init__(self, config: SimConfig, sensor_px: int, rng: np.random.Generator):
        self.config = config
        self.sensor_px = int(sensor_px)
        self.rng = rng
        map_rows, map_cols, inside = raw_to_sensor_maps(self.sensor_px)
        self._map1, self._map2 = cv2.convertMaps(map_cols, map_rows, cv2.CV_16SC2)
        self.inside = inside
        self._housing = self._make_housing(inside, rng)
        h, w = RAW_HW
        self._noise = noise_tiles(rng, config.raw_noise_std, (h + _NOISE_PAD, w + _NOISE_PAD))

    def _make_housing(self, inside: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        h, w = RAW_HW
        dist = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 5)
        level = HOUSING_LEVEL + HOUSING_GLOW * np.exp(-dist / HOUSING_GLOW_PX)
        texture = cv2.resize(
            rng.standard_normal((16, 20)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
        )
        level = level * (1 + 0.15 * texture)
        row0, col0, side = reference_square(RAW_HW)
        _, ifoc = reference_focal_lengths(side)
        v, u = np.mgrid[0:h, 0:w]
        r = np.hypot(v - (row0 + (side - 1) / 2), u - (col0 + (side - 1) / 2))
        level = np.where(r / ifoc < math.pi / 2, level, 0.0)  # outside the image circle
        level *= np.clip(1.2 - r / (ifoc * math.pi / 2), 0.0, 1.0)  # lens vignetting
        bgr = np.stack([level * 1.0, level * 0.97, level * 0.92], axis=-1)
        return np.clip(bgr, 0, 255).astype(np.uint8)

    def render(self, sensor_rgb: np.ndarray) -> np.ndarray:
        """sensor_rgb: (M, M, 3) uint8 RGB, noise-free -> (1024, 1280, 3) uint8 BGR."""
        if sensor_rgb.shape != (self.sensor_px, self.sensor_px, 3):
            raise ValueError(
                f"RawCamera.render: expected a ({self.sensor_px}, {self.sensor_px}, 3) image, "
                f"got {sensor_rgb.shape}"
            )
        src = cv2.cvtColor(sensor_rgb, cv2.COLOR_RGB2BGR)
        raw = self._housing.copy()
        cv2.remap(
            src,
            self._map1,
            self._map2,
            cv2.INTER_LINEAR,
            dst=raw,
            borderMode=cv2.BORDER_TRANSPARENT,
        )
        if self._noise:
            plus, minus = self._noise[int(self.rng.integers(len(self._noise)))]
            oy, ox = (int(v) for v in self.rng.integers(0, _NOISE_PAD, 2))
            h, w = RAW_HW
            cv2.add(raw, plus[oy : oy + h, ox : ox + w], dst=raw)
            cv2.subtract(raw, minus[oy : oy + h, ox : ox + w], dst=raw)
        if self.config.raw_jpeg_quality is not None:
            raw = jpeg_roundtrip(raw, self.config.raw_jpeg_quality, rgb=False)
        return raw
