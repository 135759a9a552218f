"""The camera's lens: OpenCV's fisheye model (K, D) fitted to checkerboard views
(:func:`fit_fisheye_lens`), its JSON file (:class:`FisheyeLens`, :func:`load_lens`) and
its undistortion maps (:func:`undistort_maps`).

``--preprocess lens.json`` (``process``, ``predict``, ``live``) undistorts with such a file
(:meth:`beadsight.preprocess.Preprocessor.from_fisheye_lens`) instead of the reference unwarp.
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

logger = logging.getLogger(__name__)

LENS_FORMAT = "beadsight-fisheye-calibration"  # the files' tag, kept so earlier files load
MIN_BOARD_VIEWS = 3  # cv2.fisheye.calibrate needs several board poses


class LensError(BeadSightError, ValueError):
    """Fitting the lens failed or a lens file is malformed; the message names it."""


@dataclass(frozen=True)
class FisheyeLens:
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
            raise LensError(f"K must be 3x3, got shape {k.shape}")
        if d.shape != (4,):
            raise LensError(f"D must have 4 coefficients (k1..k4), got {d.size}")
        if not (np.isfinite(k).all() and np.isfinite(d).all()):
            raise LensError("K and D must be finite")
        if not (k[0, 0] > 0 and k[1, 1] > 0):  # 0 maps every pixel to one point
            raise LensError(
                f"K's focal lengths fx, fy must be > 0 px, got {k[0, 0]:g}, {k[1, 1]:g}"
            )
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "D", d)
        object.__setattr__(self, "image_hw", (int(self.image_hw[0]), int(self.image_hw[1])))
        object.__setattr__(self, "pattern", (int(self.pattern[0]), int(self.pattern[1])))

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": LENS_FORMAT,
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
    def from_dict(cls, data: dict[str, Any], source: str = "lens") -> FisheyeLens:
        if data.get("format") != LENS_FORMAT:
            raise LensError(
                f"{source}: field 'format' is {data.get('format')!r}, expected {LENS_FORMAT!r}"
            )
        missing = [k for k in ("K", "D", "image_hw") if k not in data]
        if missing:
            raise LensError(f"{source}: missing field(s) {missing}")
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
        except LensError as e:
            raise LensError(f"{source}: {e}") from None
        except (TypeError, ValueError) as e:
            raise LensError(f"{source}: malformed lens file ({e})") from None

    def save(self, path: str | Path) -> Path:
        """Write JSON atomically (a crash or full disk leaves any previous file)."""
        return atomic_write_json(path, self.to_dict())


def load_lens(path: str | Path) -> FisheyeLens:
    """Read a lens JSON file written by :meth:`FisheyeLens.save`."""
    data = read_json_object(path, LensError, "a lens JSON object")
    return FisheyeLens.from_dict(data, source=str(path))


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
    """A ``cv2.fisheye.calibrate`` flag (``cv2.fisheye.X`` in OpenCV 4, ``cv2.X`` in OpenCV 5)."""
    value = getattr(cv2.fisheye, name, None)
    return int(value if value is not None else getattr(cv2, name))


def fit_fisheye_lens(
    checkerboard_images: Iterable[np.ndarray | str | Path],
    pattern: tuple[int, int] = (9, 6),
    square_mm: float = 25.0,
) -> FisheyeLens:
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
            raise LensError(f"{name}: cannot read image")
        hw = tuple(image.shape[:2])
        if image_hw is None:
            image_hw = hw
        elif hw != image_hw:
            raise LensError(
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
    if len(image_points) < MIN_BOARD_VIEWS:
        raise LensError(
            f"found a {pattern[0]}x{pattern[1]} checkerboard in {len(image_points)} view(s); "
            f"fitting the fisheye lens needs at least {MIN_BOARD_VIEWS}"
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
        raise LensError(f"cv2.fisheye.calibrate failed: {e}") from None
    return FisheyeLens(
        K=k,
        D=d,
        image_hw=image_hw,
        rms_px=float(rms),
        views=len(image_points),
        pattern=pattern,
        square_mm=float(square_mm),
    )


def undistort_maps(
    lens: FisheyeLens,
    crop: tuple[int, int, int],
    samples: int,
    pfov_deg: float,
    undistorted_px: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(map_cols, map_rows): (samples, samples) float32 source pixel of each output sample.

    The undistorted view is a virtual perspective camera looking along the optical axis: a
    ``undistorted_px`` square with ``pfov_deg`` field of view (focal
    ``undistorted_px / (2 tan(pfov/2))``, principal point at its centre). Only the part
    ``crop = (row0, col0, size)`` of that square is mapped, on a ``samples``-square grid
    (``cv2.fisheye.initUndistortRectifyMap`` with a shifted, scaled camera matrix).
    """
    if not 0 < pfov_deg < 180:
        raise ConfigError(f"pfov_deg must be in (0, 180), got {pfov_deg}")
    r0, c0, n = crop
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
    return cv2.fisheye.initUndistortRectifyMap(
        lens.K, lens.D, np.eye(3), new_k, (samples, samples), cv2.CV_32FC1
    )
