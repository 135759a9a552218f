"""Inference backends agree with fp32 torch; auto picks one that does; mismatches are refused."""

from __future__ import annotations

import dataclasses
import importlib.util
import json

import numpy as np
import pytest
import torch

from beadsight import PressurePredictor
from beadsight.checkpoint import PressureModel
from beadsight.inference.runtimes import (
    CHOICE_FILE,
    PARITY_TOLERANCE,
    Backend,
    BackendUnavailableError,
    CudaGraphBackend,
    ParityError,
    TorchBackend,
    build_backend,
    check_parity,
    create_backend,
    probe_window,
    select_backend,
)

T = 15
HAS_CUDA = torch.cuda.is_available()

CPU_BACKENDS = [
    ("torch", "fp32", None),
    ("torch", "bf16", None),
    ("onnx", "fp32", "onnxruntime"),
    ("openvino", "fp32", "openvino"),
    ("openvino", "bf16", "openvino"),
]


def _build(model, name, precision, module, **kwargs) -> Backend:
    if module and importlib.util.find_spec(module) is None:
        pytest.skip(f"{module} is not installed")
    try:
        return build_backend(model, name, precision, cache_dir=None, **kwargs)
    except BackendUnavailableError as e:
        pytest.skip(str(e))


def _stream(n: int, size: int = 64, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, size, size, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def probe_model() -> PressureModel:
    from beadsight.checkpoint import CheckpointMeta
    from beadsight.config import ModelConfig, SensorGeometry

    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(window=T, width=8), geometry=SensorGeometry(image_size_px=64),
        pixel_mean=[120.0] * 3, pixel_std=[40.0] * 3, output_scale_kpa=10.0,
    )  # fmt: skip
    return PressureModel.create(meta)


def test_probe_window_has_a_real_peak(probe_model):
    window = probe_window(probe_model)
    assert window.shape == (1, T, 64, 64, 3) and window.dtype == np.uint8
    assert probe_model.predict(window[0]).max() > PARITY_TOLERANCE.floor_kpa
    np.testing.assert_array_equal(window, probe_window(probe_model))  # deterministic


@pytest.mark.parametrize("name, precision, module", CPU_BACKENDS)
def test_backend_agrees_with_torch(probe_model, name, precision, module):
    backend = _build(probe_model, name, precision, module)
    window = probe_window(probe_model)
    out = backend.run(window)
    assert out.shape == (1, 64, 64) and out.dtype == np.float32
    parity = check_parity(backend, probe_model)
    if precision == "fp32":
        assert parity.ok and parity.max_abs_err_kpa <= 1e-4, str(parity)
    else:  # bf16 may miss the 1 % bound; then it must be refused, never silently used
        assert parity.max_abs_err_pct < 5.0, str(parity)  # really computing, in bf16
        if parity.ok:
            create_backend(probe_model, name, precision, cache_dir=None)
        else:
            with pytest.raises(ParityError, match=f"{name}/bf16 disagrees with fp32 torch"):
                create_backend(probe_model, name, precision, cache_dir=None)
    # a second window gives a different answer (the backend is not replaying a cache)
    other = _stream(T, seed=7)[None]
    np.testing.assert_allclose(
        backend.run(other)[0], probe_model.predict(other[0]),
        atol=5 * PARITY_TOLERANCE.tolerance_kpa(parity.peak_kpa), rtol=0,
    )  # fmt: skip
    backend.close()


@pytest.mark.slow
def test_compile_backend_agrees_and_is_cached(probe_model, tmp_path):
    backend = build_backend(probe_model, "compile", "fp32", cache_dir=tmp_path)
    parity = check_parity(backend, probe_model)
    assert parity.ok and parity.max_abs_err_kpa <= 1e-4, str(parity)
    again = build_backend(probe_model, "compile", "fp32", cache_dir=tmp_path)
    assert again.path == backend.path and backend.path.is_file()


def _incremental_matches_run(backend: Backend, model: PressureModel, frames: np.ndarray):
    """Stream frames through run_incremental (1 new frame per call, a jump of 3, a full
    refill, a stateless run in between) and compare each output with model.predict."""
    t = model.window
    steps = [(k, 1) for k in range(t, t + 6)] + [(t + 8, 3), (t + 30, t), (t + 31, 1)]
    backend.run_incremental(frames[None, 0:t], t)
    for i, (end, new) in enumerate(steps):
        if i == 3:  # a stateless run in between must not disturb the stream
            backend.run(_stream(t, seed=11)[None])
        window = frames[None, end - t + 1 : end + 1]
        got = backend.run_incremental(np.ascontiguousarray(window), new)
        np.testing.assert_allclose(got[0], model.predict(window[0]), atol=1e-4, rtol=0)


@pytest.fixture(scope="module")
def strided_model(probe_model) -> PressureModel:
    """probe_model's weights, seeing every 3rd frame of a 43-frame window."""
    meta = dataclasses.replace(
        probe_model.meta, model=dataclasses.replace(probe_model.meta.model, frame_stride=3)
    )
    model = PressureModel.create(meta)
    model.module.load_state_dict(probe_model.module.state_dict())
    return model


def test_strided_model_sees_every_stride_th_frame(probe_model, strided_model):
    frames = _stream(strided_model.window)
    assert strided_model.window == 3 * (T - 1) + 1
    np.testing.assert_allclose(
        strided_model.predict(frames), probe_model.predict(frames[::3]), atol=1e-6, rtol=0
    )
    changed = frames.copy()
    changed[1] = 255 - changed[1]  # a frame between two the network sees
    np.testing.assert_array_equal(strided_model.predict(changed), strided_model.predict(frames))


def test_torch_incremental_normalisation_matches_stateless(probe_model, strided_model):
    _incremental_matches_run(TorchBackend(probe_model), probe_model, _stream(T + 32))
    w = strided_model.window
    _incremental_matches_run(TorchBackend(strided_model), strided_model, _stream(w + 32))


def test_device_ring_logic_on_cpu(probe_model, strided_model):
    """The CUDA backend's device ring, run eagerly on the CPU."""
    backend = CudaGraphBackend(probe_model, "fp32", device="cpu", use_graphs=False)
    _incremental_matches_run(backend, probe_model, _stream(T + 32))
    strided = CudaGraphBackend(strided_model, "fp32", device="cpu", use_graphs=False)
    _incremental_matches_run(strided, strided_model, _stream(strided_model.window + 32))
    np.testing.assert_allclose(
        backend.run(probe_window(probe_model))[0],
        probe_model.predict(probe_window(probe_model)[0]), atol=1e-5,
    )  # fmt: skip


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_cuda_graphs_agree_with_torch(probe_model, precision):
    backend = build_backend(probe_model, "cuda", precision, device="cuda")
    assert backend.use_graphs and len(backend._graphs) == T
    parity = check_parity(backend, probe_model)
    assert parity.ok, str(parity)
    if precision == "fp32":
        _incremental_matches_run(backend, probe_model, _stream(T + 32))
    backend.close()


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
def test_predictor_on_cuda_matches_cpu(probe_model):
    predictor = PressurePredictor(probe_model, backend="cuda", precision="fp32")
    frames = _stream(T + 5)
    for k, frame in enumerate(frames):
        reading = predictor.update(frame, k / 30.0)
    np.testing.assert_allclose(
        reading.pressure_kpa, probe_model.predict(frames[-T:]), atol=1e-4, rtol=0
    )


def test_cuda_without_a_gpu_is_unavailable(probe_model):
    if HAS_CUDA:
        pytest.skip("a CUDA device is present")
    with pytest.raises(BackendUnavailableError, match="CUDA"):
        build_backend(probe_model, "cuda", "fp32")


def test_auto_picks_a_backend_that_passes_parity(probe_model, tmp_path):
    backend = select_backend(probe_model, cache_dir=tmp_path)
    assert backend.parity.ok
    assert check_parity(backend, probe_model).ok
    usable = [c for c in backend.selection if c.seconds is not None]
    assert (backend.name, backend.precision) in [(c.backend, c.precision) for c in usable]
    for c in usable:  # bf16 only within half the bound, fp32 within the bound
        assert c.err_pct <= (100 if c.precision == "fp32" else 50) * PARITY_TOLERANCE.fraction
    fastest = min(usable, key=lambda c: c.seconds)
    assert (fastest.backend, fastest.precision) == (backend.name, backend.precision)
    choices = json.loads((tmp_path / CHOICE_FILE).read_text())
    (choice,) = choices.values()
    assert (choice["backend"], choice["precision"]) == (backend.name, backend.precision)
    cached = select_backend(probe_model, cache_dir=tmp_path)  # from the cached decision
    assert cached.describe() == backend.describe()


def test_auto_with_fp32_only_considers_fp32(probe_model):
    backend = create_backend(probe_model, "auto", "fp32", cache_dir=None)
    assert backend.precision == "fp32"
    assert all(c.precision == "fp32" for c in backend.selection)


def test_named_backend_that_disagrees_is_refused(probe_model, tmp_path):
    """An ONNX file whose metadata claims this checkpoint but holds other weights."""
    pytest.importorskip("onnxruntime")
    import onnx

    from beadsight.inference.export import exported_metadata, write_onnx

    torch.manual_seed(123)
    impostor = PressureModel.create(probe_model.meta)
    path = write_onnx(impostor, tmp_path / "impostor.onnx")
    proto = onnx.load(str(path))
    for entry in proto.metadata_props:  # forge the metadata
        entry.value = exported_metadata(probe_model)[entry.key]
    onnx.save(proto, str(path))
    with pytest.raises(ParityError, match="disagrees with fp32 torch"):
        PressurePredictor(probe_model, backend="onnx", exported_model=path)


def test_bad_backend_arguments(probe_model):
    with pytest.raises(ValueError, match="backend must be"):
        create_backend(probe_model, "tensorrt", cache_dir=None)
    with pytest.raises(ValueError, match="precision must be"):
        create_backend(probe_model, "torch", "fp16", cache_dir=None)
    with pytest.raises(BackendUnavailableError, match="bf16"):
        build_backend(probe_model, "onnx", "bf16", cache_dir=None)
    backend = TorchBackend(probe_model)
    with pytest.raises(ValueError, match=r"window: expected \(1, 15, 64, 64, 3\) uint8"):
        backend.run(np.zeros((1, T, 32, 32, 3), np.uint8))
