"""Raw frame -> model input: the one rule for live sensing and for ``beadsight predict``.

A model takes (S, S, 3) uint8 RGB sensor-space frames (S = the checkpoint's image
size). What a camera, a video file or the simulator delivers becomes that according
to ``preprocess``:

=====================  ===========================================================
``"auto"`` (default)   frames already S x S are used as they are (BGR ones
                       reordered to RGB); raw frames of the reference camera
                       (1280x1024) go through the reference pipeline
                       (:meth:`~beadsight.preprocess.Preprocessor.reference`);
                       any other size is refused, naming both sizes.
``"none"``             frames must already be S x S (reordered to RGB if BGR).
``"reference"``        the reference pipeline, for frames of any size (its
                       nearest-neighbour unwarp, as the reference code samples).
``"reference-linear"`` the reference pipeline with bilinear unwarp sampling.
a ``.json`` path       a fitted fisheye lens (:mod:`beadsight.lens`).
=====================  ===========================================================

Sizes in messages are width x height, as cameras are described ("1280x1024").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from beadsight.preprocess import REFERENCE_INPUT_HW, FrameSizeError, Preprocessor

PREPROCESS_AUTO = "auto"
PREPROCESS_NAMED = ("auto", "none", "reference", "reference-linear")  # or a lens .json


@dataclass(frozen=True)
class InputConverter:
    """Turns frames like the first one into model input.

    mode: what was chosen: "none" (used as they are), "reference",
    "reference-linear", or a lens file's path.
    """

    mode: str
    convert: Callable[[np.ndarray], np.ndarray]

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """image: (H, W, 3) uint8 in the source's channel order -> (S, S, 3) uint8 RGB."""
        return self.convert(image)


def check_preprocess(preprocess: str | Path | None) -> str:
    """The spec as a string (None means "auto"); a ValueError for an unknown name."""
    if preprocess is None:
        return PREPROCESS_AUTO
    text = str(preprocess).strip()
    if text in PREPROCESS_NAMED or text.lower().endswith(".json") or Path(text).is_file():
        return text
    raise ValueError(
        f"preprocess {text!r}: expected one of {', '.join(PREPROCESS_NAMED)} or a fisheye "
        "lens .json file"
    )


def _wxh(hw: tuple[int, int]) -> str:
    return f"{hw[1]}x{hw[0]}"


def _check_image(image: object, what: str) -> tuple[int, int]:
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
        raise FrameSizeError(
            f"{what}: expected (H, W, 3) colour frames, got {getattr(image, 'shape', None)}"
        )
    if image.dtype != np.uint8:
        raise FrameSizeError(f"{what}: expected uint8 frames, got {image.dtype}")
    return int(image.shape[0]), int(image.shape[1])


def _as_is(channel_order: str) -> InputConverter:
    if channel_order == "RGB":
        return InputConverter("none", lambda image: image)
    return InputConverter("none", lambda image: cv2.cvtColor(image, cv2.COLOR_BGR2RGB))


def _preprocessor(spec: str, hw: tuple[int, int], size: int) -> Preprocessor:
    if spec == "reference":
        return Preprocessor.reference(hw, size)
    if spec == "reference-linear":
        return Preprocessor.reference(hw, size, interpolation="linear")
    return Preprocessor.from_spec(spec, hw, size)  # a lens file


def _size_error(what: str, hw: tuple[int, int], size: int, spec: str) -> FrameSizeError:
    ref = _wxh(REFERENCE_INPUT_HW)
    if spec == "none":
        hint = "pass a preprocessing (reference, reference-linear or a lens .json)"
    else:
        hint = (
            f"frames of {ref} (the reference camera) go through the reference preprocessing "
            "automatically; for another camera pass a preprocessing (reference, "
            "reference-linear or a lens .json)"
        )
    return FrameSizeError(
        f"{what} delivers {_wxh(hw)} frames, but the checkpoint expects {size}x{size} "
        f"sensor-space frames (preprocess {spec!r}); {hint}"
    )


def input_converter(
    first: np.ndarray,
    channel_order: str,
    image_size: int,
    preprocess: str | Path | None = PREPROCESS_AUTO,
    what: str = "frames",
) -> InputConverter:
    """How frames like ``first`` become (S, S, 3) uint8 RGB model input (module docstring).

    first: (H, W, 3) uint8 in ``channel_order`` ("RGB" or "BGR"). image_size: S.
    what: names the frames' origin in errors ("source camera 0", "video.avi").
    Raises :class:`~beadsight.preprocess.FrameSizeError` naming both sizes.
    """
    spec = check_preprocess(preprocess)
    hw = _check_image(first, what)
    if spec in ("auto", "none") and hw == (image_size, image_size):
        return _as_is(channel_order)
    if spec == "none" or (spec == "auto" and hw != tuple(REFERENCE_INPUT_HW)):
        raise _size_error(what, hw, image_size, spec)
    pre = _preprocessor("reference" if spec == "auto" else spec, hw, image_size)
    mode = "reference" if spec == "auto" else spec
    if channel_order == "RGB":  # the preprocessor takes BGR, as cameras deliver
        return InputConverter(mode, lambda image: pre(cv2.cvtColor(image, cv2.COLOR_RGB2BGR)))
    return InputConverter(mode, pre)
