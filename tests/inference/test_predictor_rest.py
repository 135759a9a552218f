"""PressurePredictor with a rest-referenced model: the rest image API, the first-frames
default, and the rest image reaching every runtime (torch, ONNX, OpenVINO, the device
ring) through the predictor; models without a rest input run as before."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from helpers.inference import stream

from beadsight.checkpoint import load_checkpoint
from beadsight.data.rest import REST_FRAMES, average_rest, with_rest
from beadsight.inference.parity import check_parity
from beadsight.inference.predictor import PredictorSettings, PressurePredictor
from beadsight.inference.runtimes import CudaGraphBackend
from beadsight.inference.select import build_backend

FPS = 30.0


def _predictor(model, backend="torch", **settings) -> PressurePredictor:
    return PressurePredictor.from_checkpoint(
        model, backend, "fp32", cache_dir=None, settings=PredictorSettings(**settings)
    )


def _expected(model, rest: np.ndarray, frames: np.ndarray, end: int) -> np.ndarray:
    """What the model reads for the window ending at frame ``end`` against ``rest``."""
    window = frames[end - model.span + 1 : end + 1]
    return model.predict(with_rest(rest, window))


def test_the_first_frames_become_the_rest_by_default(rest_model, caplog):
    predictor = _predictor(rest_model)
    frames = stream(rest_model.span + 3, seed=2)
    assert predictor.rest is None and not predictor.ready
    with caplog.at_level(logging.INFO, logger="beadsight.inference.predictor"):
        readings = [predictor.update(f, k / FPS) for k, f in enumerate(frames)]
    first = max(rest_model.span, REST_FRAMES) - 1  # a full window and a rest image
    assert all(r is None for r in readings[:first])
    rest = average_rest(frames[:REST_FRAMES])
    np.testing.assert_array_equal(predictor.rest, rest)
    assert not predictor.rest.flags.writeable
    for end in range(first, len(frames)):
        np.testing.assert_allclose(
            readings[end].pressure_kpa, _expected(rest_model, rest, frames, end), atol=1e-5
        )
    said = [r.getMessage() for r in caplog.records if "rest image" in r.getMessage()]
    assert len(said) == 1 and "keep the pouch unloaded" in said[0]


def test_wait_returns_nothing_until_set_rest(rest_model):
    predictor = _predictor(rest_model, initial_rest="wait")
    frames = stream(rest_model.span + 4, seed=3)
    assert [predictor.update(f, k / FPS) for k, f in enumerate(frames)] == [None] * len(frames)
    assert predictor.rest is None
    rest_frames = stream(5, seed=9)
    used = predictor.set_rest(rest_frames)  # frames: averaged with the one rule
    np.testing.assert_array_equal(used, average_rest(rest_frames))
    more = stream(1, seed=4)
    reading = predictor.update(more[0], len(frames) / FPS)  # the window is already full
    all_frames = np.concatenate([frames, more])
    np.testing.assert_allclose(
        reading.pressure_kpa, _expected(rest_model, used, all_frames, len(frames)), atol=1e-5
    )


def test_set_rest_copies_and_checks(rest_model, tiny_model):
    predictor = _predictor(rest_model)
    image = stream(1, seed=5)[0]
    used = predictor.set_rest(image)
    image[:] = 0  # the caller's array is not kept
    assert used.any() and predictor.rest is used and not used.flags.writeable
    with pytest.raises(ValueError, match=r"set_rest: expected a \(64, 64, 3\) uint8 RGB image"):
        predictor.set_rest(np.zeros((32, 32, 3), np.uint8))
    with pytest.raises(ValueError, match="set_rest: expected"):
        predictor.set_rest(np.zeros((64, 64, 3), np.float32))
    with pytest.raises(ValueError, match="is not rest-referenced"):
        _predictor(tiny_model).set_rest(np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="initial_rest must be one of"):
        PredictorSettings(initial_rest="later")


def test_the_rest_survives_reset(rest_model):
    predictor = _predictor(rest_model)
    rest = predictor.set_rest(stream(1, seed=6)[0])
    predictor.reset()
    assert predictor.rest is rest


RUNTIMES = [  # the contrast-normalised rest input where it is exported (its own graph)
    ("rest_model", "torch", None),
    ("rest_model", "onnx", "onnxruntime"),
    ("rest_model", "openvino", "openvino"),
    ("rest_model", "ring", None),
    pytest.param("rest_model", "cuda", None, marks=pytest.mark.gpu),
    ("rest_norm_model", "onnx", "onnxruntime"),
    ("rest_norm_model", "openvino", "openvino"),
    pytest.param("rest_norm_model", "cuda", None, marks=pytest.mark.gpu),
]


def _runtime(model, name, module):
    if name == "ring":  # the CUDA backend's device ring, eagerly on the CPU
        return CudaGraphBackend(model, "fp32", device="cpu", use_graphs=False)
    return build_backend(model, name, "fp32", cache_dir=None)


@pytest.mark.parametrize("fixture, name, module", RUNTIMES)
def test_the_rest_reaches_every_runtime(fixture, name, module, request):
    """Streamed through the predictor, each runtime reads against the rest image in use:
    the first frames' average, then a new rest set mid-stream (a stateful runtime that
    kept the old one would fail), and agrees with fp32 torch on the parity probe; with
    the rest input as it is and contrast-normalised (``rest_norm``, exported too)."""
    rest_model = request.getfixturevalue(fixture)
    backend = _runtime(rest_model, name, module)
    if name == "cuda":
        assert backend.use_graphs  # the rest image reaches the captured graphs
    if name != "ring":
        parity = check_parity(backend, rest_model)
        assert parity.ok and parity.max_abs_err_kpa <= 1e-4, str(parity)
    predictor = PressurePredictor(rest_model, backend)
    span = rest_model.span
    frames = stream(span + 12, seed=8)
    rest = None
    for k, frame in enumerate(frames):
        if k == span + 5:
            rest = predictor.set_rest(stream(REST_FRAMES, seed=10))
        reading = predictor.update(frame, k / FPS)
        if k >= max(span, REST_FRAMES) - 1:
            rest = predictor.rest if rest is None else rest
            np.testing.assert_allclose(
                reading.pressure_kpa, _expected(rest_model, rest, frames, k), atol=1e-4, rtol=0
            )
    first = average_rest(frames[:REST_FRAMES])
    assert not np.array_equal(first, predictor.rest)  # the rest really changed
    predictor.close()


def test_a_checkpoint_without_rest_input_loads_and_runs_unchanged(tiny_model, tmp_path):
    """A checkpoint of a model without a rest input (every checkpoint before rest_input)
    loads and streams exactly as model.predict, with no rest image anywhere."""
    model = load_checkpoint(tiny_model.save(tmp_path / "old.pt"))
    assert model.rest == 0 and model.inputs == model.span
    predictor = _predictor(model)
    frames = stream(model.span + 1, size=model.image_size, seed=12)
    readings = [predictor.update(frame, k / FPS) for k, frame in enumerate(frames)]
    assert readings[: model.span - 1] == [None] * (model.span - 1)  # no wait for a rest
    assert predictor.rest is None
    np.testing.assert_allclose(readings[-1].pressure_kpa, model.predict(frames[1:]), atol=1e-4)


def test_a_rest_norm_checkpoint_keeps_its_input(rest_norm_model, tmp_path):
    """``rest_norm`` is saved with the checkpoint (format 4) and the loaded model reads as
    the saved one; a reader that did not know it would read another input."""
    model = load_checkpoint(rest_norm_model.save(tmp_path / "norm.pt"))
    assert model.meta.model.rest_norm and model.meta.model.rest_input
    images = np.stack([stream(rest_norm_model.inputs, seed=3)])
    np.testing.assert_allclose(model.predict(images), rest_norm_model.predict(images), atol=1e-6)
