"""The camera between the lit pouch and the frame: mounting, fisheye lens, crop, blur.

The reference preprocessing assumes one camera: on the sensor's axis, square to
the pouch, with the reference fisheye lens, cropped at the reference rows and
columns. A real build differs in each, and the frames a model gets differ with
it. :func:`view_maps` follows every frame pixel backwards through that chain:

1. the (mis-sized, off-centre) crop gives its position in the unwarped
   1024 px square of the reference preprocessing;
2. the reference unwarp read it as the fisheye angle ``atan(r_d / ofoc)``; the
   real lens, of focal length ``(1 + lens_focal_error)`` times the reference's
   and radial law ``r = f theta (1 + k theta^2)``, put a different angle there;
3. that ray leaves the camera, rolled about its axis and tilted (keystone: the
   tilt pivots about the point the optical axis meets the pouch, so tilt and
   offset are separate factors), and meets the bead layer;
4. the camera itself sits ``camera_offset_mm`` off the sensor's centre.

A camera with every one of these at its reference value sees exactly the
sensor-space image (no resampling at all). :class:`Exposure` then applies the
light, the lens falloff, exposure and white balance, motion blur (the exposure
reaching into the previous frame period) and defocus.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from beadsight.preprocess import REFERENCE_SQUARE_PX, reference_crop, reference_focal_lengths
from beadsight.sim.config import SimConfig
from beadsight.sim.optics.light import glare, illumination, split_illumination

_NEWTON_STEPS = 6  # solving theta (1 + k theta^2) = t: converges to ~1e-12 in 4


def camera_is_reference(config: SimConfig) -> bool:
    """True when the camera sees the pouch exactly as the reference preprocessing assumes."""
    return (
        config.camera_offset_mm == (0.0, 0.0)
        and config.camera_tilt_deg == (0.0, 0.0)
        and config.camera_roll_deg == 0.0
        and config.lens_focal_error == 0.0
        and config.lens_distortion_k == 0.0
        and config.crop_scale_error == 0.0
        and config.crop_offset_mm == (0.0, 0.0)
    )


def _true_angle(theta_ref: np.ndarray, focal_error: float, k: float) -> np.ndarray:
    """The field angle the real lens put where the reference lens would put ``theta_ref``.

    Solves ``(1 + e) theta (1 + k theta^2) = theta_ref`` by Newton's method.
    """
    theta = theta_ref / (1.0 + focal_error)
    if k == 0:
        return theta
    for _ in range(_NEWTON_STEPS):
        f = (1.0 + focal_error) * theta * (1.0 + k * theta * theta) - theta_ref
        df = (1.0 + focal_error) * (1.0 + 3.0 * k * theta * theta)
        theta = theta - f / df
    return theta


def _tilted(vr: np.ndarray, vc: np.ndarray, config: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """Rays (vr, vc, 1) rolled and tilted -> where they meet the plane z = 1 (same units)."""
    roll = math.radians(config.camera_roll_deg)
    cr, sr = math.cos(roll), math.sin(roll)
    vr, vc = vr * cr - vc * sr, vr * sr + vc * cr
    a, b = (math.radians(t) for t in config.camera_tilt_deg)
    vz = np.ones_like(vr)
    vr, vz = vr * math.cos(a) + vz * math.sin(a), vz * math.cos(a) - vr * math.sin(a)
    vc, vz = vc * math.cos(b) + vz * math.sin(b), vz * math.cos(b) - vc * math.sin(b)
    return vr / vz, vc / vz


def view_maps(config: SimConfig, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of a ``size`` frame looks in the pouch's ``size`` sensor-space image.

    returns: ``(map_cols, map_rows)``, each (S, S) float32, pixel centres at integers
    (as ``cv2.remap`` wants). For :func:`camera_is_reference` configs, the identity.
    """
    side = REFERENCE_SQUARE_PX
    ofoc, _ = reference_focal_lengths(side)
    r0, c0, n = reference_crop(side)
    centre = (side - 1) // 2
    ppm = n / config.sensor_size_mm  # unwarped-square pixels per mm on the bead layer
    frac = (np.arange(size) + 0.5) / size - 0.5  # -0.5..0.5 across the frame
    span = n * (1.0 + config.crop_scale_error)
    ox, oy = config.crop_offset_mm  # printer +X is image -column, +Y image -row
    a = (r0 + (n - 1) / 2 - oy * ppm + frac * span)[:, None] - centre  # rows from the axis
    b = (c0 + (n - 1) / 2 - ox * ppm + frac * span)[None, :] - centre  # columns
    a, b = np.broadcast_arrays(a, b)
    r_d = np.hypot(a, b)
    theta = _true_angle(np.arctan(r_d / ofoc), config.lens_focal_error, config.lens_distortion_k)
    scale = np.divide(np.tan(theta), r_d, out=np.full_like(r_d, 1.0 / ofoc), where=r_d > 1e-9)
    vr, vc = _tilted(a * scale, b * scale, config)
    pr, pc = _tilted(np.zeros(1), np.zeros(1), config)  # the optical axis: the tilt's pivot
    cx, cy = config.camera_offset_mm
    rows = centre + ofoc * (vr - pr[0]) - cy * ppm  # unwarped-square pixels of the pouch
    cols = centre + ofoc * (vc - pc[0]) - cx * ppm
    map_rows = (rows - r0 + 0.5) / n * size - 0.5
    map_cols = (cols - c0 + 0.5) / n * size - 0.5
    return map_cols.astype(np.float32), map_rows.astype(np.float32)


class Exposure:
    """Radiance of the pouch -> uint8 frame: light, camera view, gain, blur, glare.

    config: the build; size: the frame side S; border_radiance: (3,) radiance of
    what lies beyond the sensor-space image (the pouch's seam), which a camera that
    looks off-centre sees at the frame's edge. Stateful only for motion blur (it
    keeps the previous frame's image); frame-to-frame randomness is the caller's.
    """

    def __init__(self, config: SimConfig, size: int, border_radiance=(0.0, 0.0, 0.0)):
        self.size = int(size)
        self._glare = glare(config, self.size)
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        if camera_is_reference(config):
            self._illumination = illumination(config, self.size)
        else:
            cols, rows = view_maps(config, self.size)
            reach = max(-cols.min(), -rows.min(), cols.max(), rows.max()) - (self.size - 1)
            self._pad = int(math.ceil(max(reach, 0.0))) + 2
            self._border = [float(c) for c in border_radiance]
            self._world, self._lens = split_illumination(config, self.size, self._pad)
            self._maps = cv2.convertMaps(cols + self._pad, rows + self._pad, cv2.CV_16SC2)
        self._blur = float(config.motion_blur_fraction)
        self._defocus_px = config.defocus_sigma_mm * self.size / config.sensor_size_mm
        self._previous: np.ndarray | None = None

    def __call__(self, radiance: np.ndarray, gain: float = 1.0) -> np.ndarray:
        """radiance: (S, S, 3) float32 (overwritten); gain: flicker -> (S, S, 3) uint8."""
        if self._maps is None:
            cv2.multiply(radiance, self._illumination, dst=radiance, scale=gain)
            image = radiance
        else:
            p = self._pad
            padded = cv2.copyMakeBorder(
                radiance, p, p, p, p, cv2.BORDER_CONSTANT, None, self._border
            )
            cv2.multiply(padded, self._world, dst=padded)
            image = cv2.remap(padded, *self._maps, cv2.INTER_LINEAR)
            cv2.multiply(image, self._lens, dst=image, scale=gain)
        if self._blur > 0:
            previous = self._previous if self._previous is not None else image
            self._previous = image.copy()
            image = cv2.addWeighted(image, 1.0 - self._blur, previous, self._blur, 0.0)
        if self._defocus_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), self._defocus_px)
        frame = cv2.convertScaleAbs(image)  # round and saturate to 0..255
        cv2.add(frame, self._glare, dst=frame)  # uint8 from here: saturating and fast
        return frame
