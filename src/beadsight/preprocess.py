"""Camera frame -> sensor-space image: fisheye unwarp, crop, resize, channel order.

The reference pipeline (reference-facts section 2) turns a raw 1280x1024 BGR
fisheye frame into a 256x256 sensor-space image:

1. centre square crop of side ``min(H, W)`` (1280x1024 -> columns 128..1151);
2. "defisheye" remap (fov 180 deg, pfov 120 deg, linear model, full frame): for the
   1024 px square, centre ``c = 511``, ``dim = sqrt(2) * 1024``, output focal length
   ``ofoc = dim / (2 tan 60 deg)``, input focal length ``ifoc = dim * 180 / (fov * pi)``;
   a destination pixel at radius ``r_d`` from the centre samples the source radius
   ``r_s = ifoc * atan(r_d / ofoc)``;
3. crop rows 142..891, columns 120..869 (750 x 750);
4. resize to the output size.

:class:`Preprocessor` composes steps 1-3 into ONE precomputed ``cv2.remap`` table
from the raw frame to the 750 x 750 crop (so a frame is touched once), then
resizes. ``interpolation="reference"`` reproduces the reference sampling bit for
bit: nearest neighbour with the source coordinate *truncated* (not rounded), and
the reference's quirk that the single pixel at the exact centre (``r_d == 0``)
samples the square's corner pixel (0, 0). ``interpolation="linear"`` samples the
continuous source coordinate bilinearly (the centre maps to the centre).

Resizing (step 4) is explicit about antialiasing: ``resize="area"`` (default) uses
``cv2.INTER_AREA``, which averages every source pixel under an output pixel (an
antialiased downscale, 750 -> 256 is 2.93x; exact but ~4 ms a frame);
``resize="linear"`` uses ``cv2.INTER_LINEAR`` without antialiasing (a plain
``cv2.resize``: fast, aliases fine bead texture); ``resize="supersample"`` (with
``interpolation="linear"``) puts the resize into the remap table too: it samples
the crop on a 2S x 2S grid and averages 2x2 blocks (antialiased, ~1 ms).
:meth:`Preprocessor.for_reduced_input` adapts a table to JPEG frames decoded at
1/2, 1/4 or 1/8 size (much cheaper to decode); ``beadsight process`` uses it.

Frames arrive in OpenCV BGR order; the output is RGB (this project's convention)
unless ``channel_order="BGR"`` is asked for (the reference stores BGR).

With a fitted lens (:mod:`beadsight.lens`) instead: :meth:`Preprocessor.from_fisheye_lens`,
a perspective view of the same 120 degree field of view, cropped like the reference.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from beadsight.errors import BeadSightError, ConfigError

if TYPE_CHECKING:
    from beadsight.lens import FisheyeLens

logger = logging.getLogger(__name__)

# --- reference constants (reference-facts section 2) --------------------------------
REFERENCE_INPUT_HW = (1024, 1280)  # raw camera frame, rows x columns
REFERENCE_FOV_DEG = 180.0  # fisheye lens aperture
REFERENCE_PFOV_DEG = 120.0  # perspective (output) field of view
REFERENCE_SQUARE_PX = 1024  # side of the centre square the constants below refer to
REFERENCE_CROP_PX = (142, 120, 750)  # (first row, first column, side) of the unwarped crop
REFERENCE_OUTPUT_SIZE = 256  # sensor-space image side

INTERPOLATIONS = ("reference", "linear")
RESIZES = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "supersample": cv2.INTER_AREA}
CHANNEL_ORDERS = ("RGB", "BGR")

SUPERSAMPLE_MIN_RATIO = 1.5  # supersample only when >= this many input px per output px


class FrameSizeError(BeadSightError, ValueError):
    """A frame does not have the size, channels or dtype a preprocessor was built for."""


# --- the reference defisheye model -------------------------------------------------
def reference_square(input_hw: tuple[int, int]) -> tuple[int, int, int]:
    """Centre square of a frame as the reference crops it: ``(row0, col0, side)``.

    The reference takes ``x0 = W//2 - dim//2`` and ``xf = W//2 + dim//2`` with
    ``dim = min(H, W)``, so the side is ``2 * (dim // 2)``.
    """
    h, w = (int(v) for v in input_hw)
    half = min(h, w) // 2
    return h // 2 - half, w // 2 - half, 2 * half


def reference_focal_lengths(
    side_px: int, fov_deg: float = REFERENCE_FOV_DEG, pfov_deg: float = REFERENCE_PFOV_DEG
) -> tuple[float, float]:
    """``(ofoc, ifoc)`` in pixels for a ``side_px`` square, "fullframe" linear model.

    ``dim = sqrt(side^2 + side^2)``; ``ofoc = dim / (2 tan(pfov/2))``;
    ``ifoc = dim * 180 / (fov * pi)``. For 1024 px: ~418.05 and ~460.96.
    """
    dim = math.sqrt(side_px**2.0 + side_px**2.0)
    ofoc = dim / (2 * math.tan(pfov_deg * math.pi / 360))
    ifoc = dim * 180 / (fov_deg * math.pi)
    return ofoc, ifoc


def reference_source_radius(r_dest_px, side_px: int = REFERENCE_SQUARE_PX, **fov) -> np.ndarray:
    """Source radius sampled by destination radius ``r_dest_px``: ``ifoc * atan(r_d / ofoc)``."""
    ofoc, ifoc = reference_focal_lengths(side_px, **fov)
    return ifoc * np.arctan(np.asarray(r_dest_px, dtype=np.float64) * (1.0 / ofoc))


def reference_crop(side_px: int) -> tuple[int, int, int]:
    """The reference crop ``(row0, col0, size)`` for a ``side_px`` unwarped square.

    Exact for 1024 (142, 120, 750); other sides scale it proportionally.
    """
    if side_px == REFERENCE_SQUARE_PX:
        return REFERENCE_CROP_PX
    scale = side_px / REFERENCE_SQUARE_PX
    r0, c0, n = REFERENCE_CROP_PX
    return round(r0 * scale), round(c0 * scale), max(1, round(n * scale))


def crop_sample_grid(size_px: int, samples: int) -> np.ndarray:
    """Coordinates (pixel centres at integers) of ``samples`` evenly spaced points that
    tile ``size_px`` pixels, as ``cv2.resize`` places them: ``(k + 0.5) * size / samples - 0.5``."""
    return (np.arange(samples) + 0.5) * (size_px / samples) - 0.5


def reference_maps(
    input_hw: tuple[int, int],
    *,
    truncate: bool = True,
    samples: int | None = None,
    fov_deg: float = REFERENCE_FOV_DEG,
    pfov_deg: float = REFERENCE_PFOV_DEG,
) -> tuple[np.ndarray, np.ndarray]:
    """Source coordinates of the pixels of the reference 750x750 crop.

    returns: ``(rows, cols)``, each (n, n) float64, in raw-frame pixel coordinates
    (pixel ``i`` centred at ``i``). With ``truncate`` the coordinates are the
    reference's truncated integers (and the exact centre samples the square's
    corner, as the reference does); without, continuous. ``samples`` (continuous
    only) evaluates the mapping on a ``samples x samples`` grid tiling the crop
    instead of at its ``n x n`` pixel centres.
    """
    row0, col0, side = reference_square(input_hw)
    centre = (side - 1) // 2
    r0, c0, n = reference_crop(side)
    if samples is not None and samples != n and truncate:
        raise ConfigError("truncated (reference) sampling is defined only at the crop's pixels")
    # Same operations in the same order as the reference, so truncation agrees bit for bit.
    dim = np.sqrt(side**2.0 + side**2.0)
    ofoc = dim / (2 * np.tan(pfov_deg * np.pi / 360))
    ofocinv = 1.0 / ofoc
    ifoc = dim * 180 / (fov_deg * np.pi)
    if samples is None or samples == n:
        u = np.arange(n)
    else:
        u = crop_sample_grid(n, samples)
    a, b = np.meshgrid(u + r0, u + c0, indexing="ij")
    xd = a - centre
    yd = b - centre
    rd = np.hypot(xd, yd)
    rr = ifoc * np.arctan(ofocinv * rd)
    nonzero = rd != 0
    scale = np.divide(rr, rd, out=np.zeros_like(rr), where=nonzero)
    src_r = scale * xd + centre
    src_c = scale * yd + centre
    if truncate:
        src_r = np.where(nonzero, np.trunc(src_r), 0.0)
        src_c = np.where(nonzero, np.trunc(src_c), 0.0)
    else:
        src_r = np.where(nonzero, src_r, float(centre))
        src_c = np.where(nonzero, src_c, float(centre))
    return src_r + row0, src_c + col0


# --- the preprocessor ---------------------------------------------------------------
def sample_count(resize: str, crop_px: int, output_size: int) -> int:
    """Side of the remap grid: the crop's own pixels, or 2x the output to supersample."""
    return 2 * output_size if resize == "supersample" else crop_px


@dataclass
class Preprocessor:
    """Raw camera frame (BGR) -> sensor-space image (RGB by default).

    Build it with :meth:`reference`, :meth:`from_fisheye_lens` or
    :meth:`identity`; call it on frames::

        pre = Preprocessor.reference(input_hw=(1024, 1280), output_size=256)
        image = pre(frame_bgr)  # (1024, 1280, 3) uint8 BGR -> (256, 256, 3) uint8 RGB

    A remap table (``map_rows``/``map_cols``: (M, M) float32 input-frame pixel
    coordinates of every intermediate pixel) does the geometry in one pass; without
    one, the frame is centre-cropped (``crop``). The intermediate image is then
    resized to ``output_size``:

    * ``resize="area"``: ``cv2.INTER_AREA`` (antialiased: averages every source pixel
      under an output pixel); exact but the slowest (~4 ms for 750 -> 256);
    * ``resize="linear"``: ``cv2.INTER_LINEAR`` (no antialiasing; what a plain
      ``cv2.resize`` does, fast);
    * ``resize="supersample"``: the remap table samples the crop directly on a
      ``2S x 2S`` grid (bilinear) and a 2x2 box average gives ``S x S``: antialiased
      and fast; needs ``interpolation="linear"``.

    Instances are thread-safe (calls share only read-only tables).
    """

    input_hw: tuple[int, int]
    output_size: int
    map_rows: np.ndarray | None = field(default=None, repr=False)
    map_cols: np.ndarray | None = field(default=None, repr=False)
    interpolation: str = "linear"
    crop: tuple[int, int, int, int] | None = None  # (row0, col0, height, width) without maps
    resize: str = "area"
    channel_order: str = "RGB"
    description: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.input_hw = (int(self.input_hw[0]), int(self.input_hw[1]))
        if min(self.input_hw) < 1:
            raise ConfigError(f"input_hw must be positive, got {self.input_hw}")
        if int(self.output_size) != self.output_size or self.output_size < 1:
            raise ConfigError(f"output_size must be a positive integer, got {self.output_size}")
        self.output_size = int(self.output_size)
        check_choice("interpolation", self.interpolation, INTERPOLATIONS)
        check_choice("resize", self.resize, tuple(RESIZES))
        check_choice("channel_order", self.channel_order, CHANNEL_ORDERS)
        if self.resize == "supersample" and self.interpolation != "linear":
            raise ConfigError('resize="supersample" needs interpolation="linear"')
        self._fast_maps: tuple[np.ndarray, np.ndarray | None] | None = None
        if self.map_rows is not None:
            if self.map_cols is None or self.map_rows.shape != self.map_cols.shape:
                raise ConfigError("map_rows and map_cols must be given together, same shape")
            self.map_rows = np.ascontiguousarray(self.map_rows, dtype=np.float32)
            self.map_cols = np.ascontiguousarray(self.map_cols, dtype=np.float32)
            # Fixed-point maps: cv2.remap's fastest path.
            if self.interpolation == "reference":
                m1, _ = cv2.convertMaps(
                    self.map_cols, self.map_rows, cv2.CV_16SC2, nninterpolation=True
                )
                self._fast_maps = (m1, None)
            else:
                self._fast_maps = cv2.convertMaps(self.map_cols, self.map_rows, cv2.CV_16SC2)

    # --- constructors ---------------------------------------------------------------
    @classmethod
    def reference(
        cls,
        input_hw: tuple[int, int] = REFERENCE_INPUT_HW,
        output_size: int = REFERENCE_OUTPUT_SIZE,
        *,
        interpolation: str = "reference",
        resize: str = "area",
        channel_order: str = "RGB",
    ) -> Preprocessor:
        """The reference pipeline (centre square, defisheye, crop 750, resize).

        ``interpolation="reference"``: nearest neighbour by truncation, bit-compatible
        with the reference up to the resize (``resize="linear"`` is a plain
        ``cv2.resize``); ``"linear"``: bilinear sampling of the continuous source
        coordinate.
        """
        check_choice("interpolation", interpolation, INTERPOLATIONS)
        check_choice("resize", resize, tuple(RESIZES))
        _, _, side = reference_square(input_hw)
        crop = reference_crop(side)
        samples = sample_count(resize, crop[2], output_size)
        rows, cols = reference_maps(
            input_hw, truncate=interpolation == "reference", samples=samples
        )
        return cls(
            input_hw=tuple(input_hw),
            output_size=output_size,
            map_rows=rows,
            map_cols=cols,
            interpolation=interpolation,
            resize=resize,
            channel_order=channel_order,
            description={
                "kind": "reference",
                "fov_deg": REFERENCE_FOV_DEG,
                "pfov_deg": REFERENCE_PFOV_DEG,
                "square": list(reference_square(input_hw)),
                "crop": list(crop),
            },
        )

    @classmethod
    def identity(
        cls,
        output_size: int,
        input_hw: tuple[int, int] | None = None,
        *,
        resize: str = "area",
        channel_order: str = "RGB",
    ) -> Preprocessor:
        """No unwarp: centre square crop (if the input is not square) and resize.

        For frames that are already sensor-space images (e.g. the simulator's
        ``render()``). ``input_hw`` defaults to ``(output_size, output_size)``.
        """
        input_hw = tuple(input_hw) if input_hw is not None else (output_size, output_size)
        h, w = input_hw
        side = min(h, w)
        crop = ((h - side) // 2, (w - side) // 2, side, side)
        return cls(
            input_hw=input_hw,
            output_size=output_size,
            crop=crop,
            resize="area" if resize == "supersample" else resize,
            channel_order=channel_order,
            description={"kind": "none", "crop": list(crop)},
        )

    @classmethod
    def from_fisheye_lens(
        cls,
        lens: FisheyeLens,
        output_size: int = REFERENCE_OUTPUT_SIZE,
        *,
        input_hw: tuple[int, int] | None = None,
        pfov_deg: float = REFERENCE_PFOV_DEG,
        undistorted_px: int = REFERENCE_SQUARE_PX,
        crop: tuple[int, int, int] | None = None,
        resize: str = "area",
        channel_order: str = "RGB",
    ) -> Preprocessor:
        """Undistort with a fitted fisheye lens to a ``undistorted_px`` perspective square
        of ``pfov_deg`` field of view (:func:`beadsight.lens.undistort_maps`), crop
        ``(row0, col0, size)`` of it (default: the reference crop scaled to
        ``undistorted_px``) and resize, bilinearly."""
        from beadsight.lens import undistort_maps

        input_hw = tuple(input_hw) if input_hw is not None else lens.image_hw
        if tuple(input_hw) != tuple(lens.image_hw):
            raise FrameSizeError(
                f"the lens was fitted on {lens.image_hw[1]}x{lens.image_hw[0]} frames but the "
                f"preprocessor is for {input_hw[1]}x{input_hw[0]} frames"
            )
        check_choice("resize", resize, tuple(RESIZES))
        r0, c0, n = crop if crop is not None else reference_crop(undistorted_px)
        samples = sample_count(resize, int(n), output_size)
        map_x, map_y = undistort_maps(lens, (r0, c0, n), samples, pfov_deg, undistorted_px)
        description = {"kind": "fisheye-lens", "K": lens.K.tolist(), "D": lens.D.tolist()}
        description |= {"pfov_deg": pfov_deg, "undistorted_px": undistorted_px}
        return cls(
            input_hw=input_hw,
            output_size=output_size,
            map_rows=map_y,
            map_cols=map_x,
            interpolation="linear",
            resize=resize,
            channel_order=channel_order,
            description={**description, "crop": [int(r0), int(c0), int(n)]},
        )

    @classmethod
    def from_spec(
        cls,
        spec: str | Path,
        input_hw: tuple[int, int],
        output_size: int,
        *,
        interpolation: str = "reference",
        resize: str = "area",
    ) -> Preprocessor:
        """Build from a CLI spec: ``"reference"``, ``"none"`` or a lens JSON file's path.

        ``interpolation`` applies to ``"reference"``; ``resize`` to all.
        """
        text = str(spec)
        if text == "reference":
            return cls.reference(input_hw, output_size, interpolation=interpolation, resize=resize)
        if text == "none":
            return cls.identity(output_size, input_hw, resize=resize)
        path = Path(text)
        if path.suffix.lower() == ".json" or path.exists():
            from beadsight.lens import load_lens

            return cls.from_fisheye_lens(
                load_lens(path), output_size, input_hw=input_hw, resize=resize
            )
        raise ConfigError(
            f"preprocess {text!r}: expected 'reference', 'none' or a fisheye lens .json file"
        )

    def for_reduced_input(self, factor: int) -> Preprocessor:
        """The same preprocessing for frames decoded at ``1/factor`` size.

        JPEG decoders can decode at 1/2, 1/4, 1/8 scale for a fraction of the cost
        (``cv2.IMREAD_REDUCED_COLOR_2``...); the remap table is rescaled to match
        (sizes round up, as libjpeg does). Only for continuous (``"linear"``)
        sampling: truncated reference sampling cannot be rescaled exactly.
        """
        if factor == 1:
            return self
        if self.map_rows is None or self.interpolation != "linear":
            raise ConfigError(
                "for_reduced_input needs a remap table with interpolation='linear' "
                f"(this one: interpolation={self.interpolation!r})"
            )
        h, w = self.input_hw
        rows, cols = self.map_rows, self.map_cols
        s = self.output_size
        if (
            self.resize == "supersample"
            and rows.shape == (2 * s, 2 * s)
            and self._source_span_px() / factor / s < SUPERSAMPLE_MIN_RATIO
        ):
            # Little downscaling is left after the reduced decode (which already low-passes):
            # sample each output pixel once, at the centre of its 2x2 supersamples.
            rows = rows.reshape(s, 2, s, 2).mean(axis=(1, 3))
            cols = cols.reshape(s, 2, s, 2).mean(axis=(1, 3))
        return Preprocessor(
            input_hw=(-(-h // factor), -(-w // factor)),
            output_size=self.output_size,
            map_rows=(rows + 0.5) / factor - 0.5,
            map_cols=(cols + 0.5) / factor - 0.5,
            interpolation=self.interpolation,
            resize=self.resize,
            channel_order=self.channel_order,
            description={**self.description, "decode_scale": factor},
        )

    def _source_span_px(self) -> float:
        """Input pixels spanned by the mapped region, along its narrower direction."""
        assert self.map_rows is not None and self.map_cols is not None
        return min(
            float(np.ptp(self.map_rows[:, self.map_rows.shape[1] // 2])),
            float(np.ptp(self.map_cols[self.map_cols.shape[0] // 2, :])),
        )

    def max_reduction(self) -> int:
        """Largest JPEG decode reduction (1, 2, 4 or 8) that keeps at least one input
        pixel per output pixel across the mapped region (1 if not rescalable)."""
        if self.map_rows is None or self.interpolation != "linear":
            return 1
        span = self._source_span_px()
        factor = 1
        while factor < 8 and span / (2 * factor) >= self.output_size:
            factor *= 2
        return factor

    # --- applying ---------------------------------------------------------------------
    @property
    def intermediate_hw(self) -> tuple[int, int]:
        if self.map_rows is not None:
            return tuple(self.map_rows.shape)  # type: ignore[return-value]
        if self.crop is not None:
            return self.crop[2], self.crop[3]
        return self.input_hw

    def check(self, frame: np.ndarray, what: str = "frame") -> None:
        """Raise :class:`FrameSizeError` unless ``frame`` is (H, W, 3) uint8 of ``input_hw``."""
        h, w = self.input_hw
        if not isinstance(frame, np.ndarray) or frame.ndim != 3 or frame.shape[2] != 3:
            shape = getattr(frame, "shape", None)
            raise FrameSizeError(f"{what}: expected a ({h}, {w}, 3) uint8 BGR image, got {shape}")
        if frame.shape[:2] != (h, w):
            raise FrameSizeError(
                f"{what} is {frame.shape[1]}x{frame.shape[0]} (W x H) but the preprocessor was "
                f"built for {w}x{h} frames"
            )
        if frame.dtype != np.uint8:
            raise FrameSizeError(f"{what}: expected uint8 pixels, got {frame.dtype}")

    def __call__(self, frame_bgr: np.ndarray) -> np.ndarray:
        """frame_bgr: (H, W, 3) uint8 BGR -> (S, S, 3) uint8 in ``channel_order`` (RGB)."""
        self.check(frame_bgr)
        if self._fast_maps is not None:
            m1, m2 = self._fast_maps
            flag = cv2.INTER_NEAREST if self.interpolation == "reference" else cv2.INTER_LINEAR
            mid = cv2.remap(frame_bgr, m1, m2, flag, borderMode=cv2.BORDER_REPLICATE)
        elif self.crop is not None:
            r0, c0, h, w = self.crop
            mid = frame_bgr[r0 : r0 + h, c0 : c0 + w]
        else:
            mid = frame_bgr
        s = self.output_size
        if mid.shape[:2] != (s, s):
            mid = cv2.resize(mid, (s, s), interpolation=RESIZES[self.resize])
        if self.channel_order == "RGB":
            return cv2.cvtColor(mid, cv2.COLOR_BGR2RGB)
        return np.ascontiguousarray(mid)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description (for dataset provenance)."""
        return {
            **self.description,
            "input_hw": list(self.input_hw),
            "output_size": self.output_size,
            "interpolation": self.interpolation,
            "resize": self.resize,
            "channel_order": self.channel_order,
        }


def check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"{name} must be one of {choices}, got {value!r}")
