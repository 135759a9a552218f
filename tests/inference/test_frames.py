"""One raw-frame -> model-input rule for live sensing and `beadsight predict`."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from beadsight.inference.frames import check_preprocess, input_converter
from beadsight.preprocess import FrameSizeError, Preprocessor

S = 64
RAW_HW = (1024, 1280)  # the reference camera, rows x columns


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize("preprocess", ["auto", None, "none"])
def test_model_size_frames_are_used_as_they_are(preprocess):
    rgb = _image(S, S)
    convert = input_converter(rgb, "RGB", S, preprocess)
    assert convert.mode == "none"
    np.testing.assert_array_equal(convert(rgb), rgb)
    bgr = np.ascontiguousarray(rgb[..., ::-1])
    np.testing.assert_array_equal(input_converter(bgr, "BGR", S, preprocess)(bgr), rgb)


def test_auto_sends_reference_camera_frames_through_the_reference_pipeline():
    raw = _image(*RAW_HW)
    convert = input_converter(raw, "BGR", S)
    assert convert.mode == "reference"
    expected = Preprocessor.reference(RAW_HW, S)(raw)
    np.testing.assert_array_equal(convert(raw), expected)
    # an RGB source (the simulator's order) gets the same image
    rgb = np.ascontiguousarray(raw[..., ::-1])
    np.testing.assert_array_equal(input_converter(rgb, "RGB", S)(rgb), expected)


@pytest.mark.parametrize("preprocess", ["auto", "none"])
def test_other_sizes_are_refused_naming_both_sizes(preprocess):
    with pytest.raises(FrameSizeError) as info:
        input_converter(_image(48, 80), "BGR", S, preprocess, what="source camera 2")
    message = str(info.value)
    assert "source camera 2 delivers 80x48 frames" in message and f"{S}x{S}" in message
    assert "reference-linear" in message  # says what to pass instead
    if preprocess == "auto":
        assert "1280x1024" in message


def test_named_pipelines_take_any_size():
    raw = _image(80, 100)
    convert = input_converter(raw, "BGR", S, "reference")
    np.testing.assert_array_equal(convert(raw), Preprocessor.reference((80, 100), S)(raw))
    linear = input_converter(raw, "BGR", S, "reference-linear")
    assert linear.mode == "reference-linear"
    expected = Preprocessor.reference((80, 100), S, interpolation="linear")(raw)
    np.testing.assert_array_equal(linear(raw), expected)
    assert not np.array_equal(linear(raw), convert(raw))  # bilinear, not nearest


def test_bad_specs_and_frames_are_refused():
    with pytest.raises(ValueError, match="preprocess 'fisheye'.*reference-linear"):
        check_preprocess("fisheye")
    with pytest.raises(FrameSizeError, match=r"expected \(H, W, 3\) colour frames"):
        input_converter(np.zeros((S, S), np.uint8), "RGB", S)
    with pytest.raises(FrameSizeError, match="expected uint8 frames, got float32"):
        input_converter(np.zeros((S, S, 3), np.float32), "RGB", S)


def test_live_and_predict_share_the_rule(tiny_model, tmp_path):
    """A 100x80 video: refused by both under "auto", converted alike under "reference"."""
    from beadsight.evaluation.predict import PredictionError, predict_recording
    from beadsight.live.sources import frame_converter

    frames = np.stack([_image(80, 100, seed=k) for k in range(3)])
    first = SimpleNamespace(image=frames[0], channel_order="BGR")  # a camera's first frame
    with pytest.raises(FrameSizeError, match="source cam delivers 100x80 frames"):
        frame_converter(first, "cam", S)
    path = tmp_path / "raw.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (100, 80))
    for frame in frames:
        writer.write(frame)
    writer.release()
    with pytest.raises(PredictionError, match="100x80 frames"):
        predict_recording(tiny_model, path, tmp_path / "o.h5", device="cpu", progress=False)
    live = frame_converter(first, "cam", S, "reference")(first)
    np.testing.assert_array_equal(live, Preprocessor.reference((80, 100), S)(frames[0]))
