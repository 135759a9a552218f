"""Fisheye calibration: OpenCV's fisheye model (K, D) fitted to checkerboard views
(:func:`calibrate_fisheye`), stored as JSON (:class:`FisheyeCalibration`,
:func:`load_calibration`), and the :class:`~beadsight.preprocess.Preprocessor` that
undistorts with it (:func:`calibrated_preprocessor`): a perspective view with the
reference's 120 degree field of view, cropped like the reference.

``beadsight process --preprocess calib.json`` and ``beadsight predict/live
--preprocess calib.json`` use such a file instead of the reference unwarp.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from beadsight.errors import BeadSightError, ConfigError
from beadsight.files import atomic_write_json, read_json_object
from beadsight.preprocess import (
    REFERENCE_OUTPUT_SIZE,
    REFERENCE_PFOV_DEG,
    REFERENCE_SQUARE_PX,
    RESIZES,
    FrameSizeError,
    Preprocessor,
    check_choice,
    reference_crop,
    sample_count,
)

logger = logging.getLogger(__name__)

CALIBRATION_FORMAT = "beadsight-fisheye-calibration"
MIN_CALIBRATION_VIEWS = 3  # cv2.fisheye.calibrate needs several board poses


class CalibrationError(BeadSightError, ValueError):
    """Fisheye calibration failed or a calibration file is malformed; the message names it."""


@dataclass(frozen=True)
class FisheyeCalibration:
    """OpenCV fisheye model of a camera.

    K: (3, 3) float64 camera matrix (pixels); D: (4,) float64 distortion k1..k4;
    image_hw: frame size (rows, cols) it was fitted on; rms_px: RMS reprojection error.
    """

    K: np.ndarray
    D: np.ndarray
    image_hw: tuple[int, int]
    rms_px: float = float("nan")
    views: int = 0
    pattern: tuple[int, int] = (9, 6)
    square_mm: float = float("nan")

    def __post_init__(self) -> None:
        k = np.asarray(self.K, dtype=np.float64)
        d = np.asarray(self.D, dtype=np.float64).reshape(-1)
        if k.shape != (3, 3):
            raise CalibrationError(f"K must be 3x3, got shape {k.shape}")
        if d.shape != (4,):
            raise CalibrationError(f"D must have 4 coefficients (k1..k4), got {d.size}")
        if not (np.isfinite(k).all() and np.isfinite(d).all()):
            raise CalibrationError("K and D must be finite")
        if not (k[0, 0] > 0 and k[1, 1] > 0):  # 0 maps every pixel to one point
            raise CalibrationError(
                f"K's focal lengths fx, fy must be > 0 px, got {k[0, 0]:g}, {k[1, 1]:g}"
            )
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "D", d)
        object.__setattr__(self, "image_hw", (int(self.image_hw[0]), int(self.image_hw[1])))
        object.__setattr__(self, "pattern", (int(self.pattern[0]), int(self.pattern[1])))

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": CALIBRATION_FORMAT,
            "model": "opencv-fisheye",
            "K": self.K.tolist(),
            "D": self.D.tolist(),
            "image_hw": list(self.image_hw),
            "rms_px": self.rms_px,
            "views": self.views,
            "pattern": list(self.pattern),
            "square_mm": self.square_mm,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "calibration") -> FisheyeCalibration:
        if data.get("format") != CALIBRATION_FORMAT:
            raise CalibrationError(
                f"{source}: field 'format' is {data.get('format')!r}, expected {CALIBRATION_FORMAT!r}"
            )
        missing = [k for k in ("K", "D", "image_hw") if k not in data]
        if missing:
            raise CalibrationError(f"{source}: missing field(s) {missing}")
        try:
            return cls(
                K=np.asarray(data["K"], dtype=np.float64),
                D=np.asarray(data["D"], dtype=np.float64),
                image_hw=tuple(data["image_hw"]),
                rms_px=float(data.get("rms_px", float("nan"))),
                views=int(data.get("views", 0)),
                pattern=tuple(data.get("pattern", (9, 6))),
                square_mm=float(data.get("square_mm", float("nan"))),
            )
        except CalibrationError as e:
            raise CalibrationError(f"{source}: {e}") from None
        except (TypeError, ValueError) as e:
            raise CalibrationError(f"{source}: malformed calibration ({e})") from None

    def save(self, path: str | Path) -> Path:
        """Write JSON atomically (a crash or full disk leaves any previous file)."""
        return atomic_write_json(path, self.to_dict())


def load_calibration(path: str | Path) -> FisheyeCalibration:
    """Read a calibration JSON written by :meth:`FisheyeCalibration.save`."""
    data = read_json_object(path, CalibrationError, "a calibration JSON object")
    return FisheyeCalibration.from_dict(data, source=str(path))


def board_points(pattern: tuple[int, int], square_mm: float) -> np.ndarray:
    """(cols*rows, 3) float64 inner-corner coordinates (mm) of a checkerboard, z = 0.

    ``pattern`` = (inner corners per row, inner corners per column), OpenCV order.
    """
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    return np.hstack([grid * float(square_mm), np.zeros((len(grid), 1))])


def find_board(image: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Inner corners of a checkerboard: (N, 2) float64 pixels, or None if not found."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_ACCURACY)
    if not found:
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
        if not found:
            return None
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float64)


def _fisheye_flag(name: str) -> int:
    """A fisheye calibration flag (``cv2.fisheye.X`` in OpenCV 4, ``cv2.X`` in OpenCV 5)."""
    value = getattr(cv2.fisheye, name, None)
    return int(value if value is not None else getattr(cv2, name))


def calibrate_fisheye(
    checkerboard_images: Iterable[np.ndarray | str | Path],
    pattern: tuple[int, int] = (9, 6),
    square_mm: float = 25.0,
) -> FisheyeCalibration:
    """Fit OpenCV's fisheye model to checkerboard views.

    checkerboard_images: (H, W, 3) uint8 BGR or (H, W) uint8 images, or image paths,
    all the same size. pattern: inner corners (per row, per column). Views where the
    board is not found are skipped (logged); at least 3 must remain.
    """
    obj = board_points(pattern, square_mm)
    object_points, image_points = [], []
    image_hw: tuple[int, int] | None = None
    skipped = []
    for k, item in enumerate(checkerboard_images):
        name = str(item) if isinstance(item, (str, Path)) else f"image {k}"
        image = cv2.imread(str(item), cv2.IMREAD_COLOR) if isinstance(item, (str, Path)) else item
        if image is None:
            raise CalibrationError(f"{name}: cannot read image")
        hw = tuple(image.shape[:2])
        if image_hw is None:
            image_hw = hw
        elif hw != image_hw:
            raise CalibrationError(
                f"{name} is {hw[1]}x{hw[0]} but earlier views are {image_hw[1]}x{image_hw[0]}"
            )
        corners = find_board(image, pattern)
        if corners is None:
            skipped.append(name)
            continue
        # (1, N, 3) / (1, N, 2) float64: the layout cv2.fisheye accepts in OpenCV 4 and 5
        object_points.append(obj.reshape(1, -1, 3))
        image_points.append(corners.reshape(1, -1, 2))
    if skipped:
        logger.warning(
            "checkerboard %s not found in %d view(s): %s",
            pattern,
            len(skipped),
            ", ".join(skipped[:10]),
        )
    if len(image_points) < MIN_CALIBRATION_VIEWS:
        raise CalibrationError(
            f"found a {pattern[0]}x{pattern[1]} checkerboard in {len(image_points)} view(s); "
            f"fisheye calibration needs at least {MIN_CALIBRATION_VIEWS}"
        )
    assert image_hw is not None
    flags = _fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | _fisheye_flag("CALIB_FIX_SKEW")
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-9)
    try:
        rms, k, d, _, _ = cv2.fisheye.calibrate(
            object_points,
            image_points,
            (image_hw[1], image_hw[0]),
            None,
            None,
            flags=flags,
            criteria=criteria,
        )
    except cv2.error as e:
        raise CalibrationError(f"cv2.fisheye.calibrate failed: {e}") from None
    return FisheyeCalibration(
        K=k,
        D=d,
        image_hw=image_hw,
        rms_px=float(rms),
        views=len(image_points),
        pattern=pattern,
        square_mm=float(square_mm),
    )


def calibrated_preprocessor(
    calibration: FisheyeCalibration,
    output_size: int = REFERENCE_OUTPUT_SIZE,
    *,
    input_hw: tuple[int, int] | None = None,
    pfov_deg: float = REFERENCE_PFOV_DEG,
    undistorted_px: int = REFERENCE_SQUARE_PX,
    crop: tuple[int, int, int] | None = None,
    resize: str = "area",
    channel_order: str = "RGB",
) -> Preprocessor:
    """Undistort with a calibrated fisheye model, then crop and resize.

    The undistorted view is a virtual perspective camera looking along the
    optical axis: a ``undistorted_px`` square with ``pfov_deg`` field of view
    (focal ``undistorted_px / (2 tan(pfov/2))``, principal point at its centre),
    like the reference's output. ``crop = (row0, col0, size)`` in that square
    (default: the reference crop scaled to ``undistorted_px``). Only the cropped
    part is mapped (``cv2.fisheye.initUndistortRectifyMap`` with a shifted,
    scaled camera matrix), bilinearly.
    """
    input_hw = tuple(input_hw) if input_hw is not None else calibration.image_hw
    if tuple(input_hw) != tuple(calibration.image_hw):
        raise FrameSizeError(
            f"calibration was made for {calibration.image_hw[1]}x{calibration.image_hw[0]} "
            f"frames but the preprocessor is for {input_hw[1]}x{input_hw[0]} frames"
        )
    if not 0 < pfov_deg < 180:
        raise ConfigError(f"pfov_deg must be in (0, 180), got {pfov_deg}")
    check_choice("resize", resize, tuple(RESIZES))
    r0, c0, n = crop if crop is not None else reference_crop(undistorted_px)
    samples = sample_count(resize, int(n), output_size)
    focal = undistorted_px / (2 * math.tan(math.radians(pfov_deg) / 2))
    centre = (undistorted_px - 1) / 2
    # Grid point k of the crop sits at undistorted pixel (k + 0.5) * n / samples - 0.5 + r0.
    step = n / samples
    new_k = np.array(
        [
            [focal / step, 0, (centre - c0 + 0.5) / step - 0.5],
            [0, focal / step, (centre - r0 + 0.5) / step - 0.5],
            [0, 0, 1],
        ],
        dtype=np.float64,
    )
    map_x, map_y = cv2.fisheye.initUndistortRectifyMap(
        calibration.K, calibration.D, np.eye(3), new_k, (samples, samples), cv2.CV_32FC1
    )
    return Preprocessor(
        input_hw=input_hw,
        output_size=output_size,
        map_rows=map_y,
        map_cols=map_x,
        interpolation="linear",
        resize=resize,
        channel_order=channel_order,
        description={
            "kind": "fisheye-calibration",
            "K": calibration.K.tolist(),
            "D": calibration.D.tolist(),
            "pfov_deg": pfov_deg,
            "undistorted_px": undistorted_px,
            "crop": [int(r0), int(c0), int(n)],
        },
    )
