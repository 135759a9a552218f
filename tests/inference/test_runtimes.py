"""Inference runtimes agree with fp32 torch, also when streaming."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.inference import T, stream
from helpers.isolated import run_isolated

from beadsight.checkpoint import PressureModel
from beadsight.inference.machine import default_threads, usable_cores
from beadsight.inference.parity import PARITY_TOLERANCE, ParityError, check_parity, probe_window
from beadsight.inference.planes import ring_inputs
from beadsight.inference.predictor import PressurePredictor
from beadsight.inference.runtimes import (
    Backend,
    BackendUnavailableError,
    CudaGraphBackend,
    TorchBackend,
    openvino_supports_bf16,
)
from beadsight.inference.select import build_backend, create_backend

HAS_CUDA = torch.cuda.is_available()

OV_BF16 = openvino_supports_bf16()  # native bf16 (AVX-512 bf16 / AMX) on this CPU
CPU_BACKENDS = [
    ("torch", "fp32", None),
    ("torch", "bf16", None),
    ("onnx", "fp32", "onnxruntime"),
    ("openvino", "fp32", "openvino"),
] + ([("openvino", "bf16", "openvino")] if OV_BF16 else [])


def test_openvino_bf16_runs_only_where_the_cpu_has_it(probe_model):
    """Where the CPU has native bf16 it builds (and CPU_BACKENDS checks its parity); elsewhere it
    is refused with a named error, never run emulated."""
    if OV_BF16:
        assert build_backend(probe_model, "openvino", "bf16", cache_dir=None).precision == "bf16"
    else:
        with pytest.raises(BackendUnavailableError, match="this CPU has no native bf16"):
            build_backend(probe_model, "openvino", "bf16", cache_dir=None)


def test_runtimes_not_told_threads_take_omp_num_threads(probe_model, monkeypatch):
    """OMP_NUM_THREADS limits ONNX Runtime and OpenVINO as torch (capped by the usable cores);
    unset or not a positive number, they take every usable core."""
    cores = usable_cores()
    for value, expected in (("1", 1), (str(cores + 8), cores), ("0", cores), ("x", cores)):
        monkeypatch.setenv("OMP_NUM_THREADS", value)
        assert default_threads() == expected, value
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert default_threads() == cores
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    openvino = build_backend(probe_model, "openvino", "fp32", cache_dir=None)
    assert openvino.compiled.get_property("INFERENCE_NUM_THREADS") == 1
    openvino.close()
    onnx = build_backend(probe_model, "onnx", "fp32", cache_dir=None)
    assert onnx.session.get_session_options().intra_op_num_threads == 1
    onnx.close()
    told = build_backend(probe_model, "openvino", "fp32", cache_dir=None, threads=2)
    assert told.compiled.get_property("INFERENCE_NUM_THREADS") == 2  # an explicit count wins
    told.close()


@pytest.mark.parametrize("name, precision, module", CPU_BACKENDS)
def test_backend_agrees_with_torch(probe_model, name, precision, module):
    backend = build_backend(probe_model, name, precision, cache_dir=None)
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
    other = stream(T, seed=7)[None]
    np.testing.assert_allclose(
        backend.run(other)[0],
        probe_model.predict(other[0]),
        atol=5 * PARITY_TOLERANCE.tolerance_kpa(parity.peak_kpa),
        rtol=0,
    )
    backend.close()


def _incremental_matches_run(backend: Backend, model: PressureModel, frames: np.ndarray):
    """Stream frames through run_incremental (1 new frame per call, a jump of 3, a full
    refill, a stateless run in between) and compare each output with model.predict."""
    t = model.span
    steps = [(k, 1) for k in range(t, t + 6)] + [(t + 8, 3), (t + 30, t), (t + 31, 1)]
    backend.run_incremental(frames[None, 0:t], t)
    for i, (end, new) in enumerate(steps):
        if i == 3:  # a stateless run in between must not disturb the stream
            backend.run(stream(t, seed=11)[None])
        window = frames[None, end - t + 1 : end + 1]
        got = backend.run_incremental(np.ascontiguousarray(window), new)
        np.testing.assert_allclose(got[0], model.predict(window[0]), atol=1e-4, rtol=0)


def test_strided_model_sees_every_stride_th_frame(probe_model, strided_model):
    frames = stream(strided_model.span)
    assert strided_model.span == 3 * (T - 1) + 1
    np.testing.assert_allclose(
        strided_model.predict(frames), probe_model.predict(frames[::3]), atol=1e-6, rtol=0
    )
    changed = frames.copy()
    changed[1] = 255 - changed[1]  # a frame between two the network sees
    np.testing.assert_array_equal(strided_model.predict(changed), strided_model.predict(frames))


def test_torch_incremental_normalisation_matches_stateless(probe_model, strided_model):
    _incremental_matches_run(TorchBackend(probe_model), probe_model, stream(T + 32))
    w = strided_model.span
    _incremental_matches_run(TorchBackend(strided_model), strided_model, stream(w + 32))


@pytest.mark.parametrize("name", ["onnx", "openvino"])
def test_file_runtimes_stream_through_the_plane_ring(probe_model, strided_model, name):
    """The file runtimes built from a checkpoint run the network on planes that each frame
    gets once; a stride keeps one ring per phase. The input handed to the runtime is a
    view into the ring, contiguous: no per-frame copy of the window."""
    for model in (probe_model, strided_model):
        backend = build_backend(model, name, "fp32", cache_dir=None)
        _incremental_matches_run(backend, model, stream(model.span + 32))
        window = stream(model.span, seed=3)[None]
        planes = backend.planes.update(window, model.span)
        assert planes.flags.c_contiguous and np.shares_memory(planes, backend.planes._slots)
        np.testing.assert_allclose(planes, ring_inputs(model.module, window), atol=1e-5, rtol=0)
        backend.close()


def test_device_ring_logic_on_cpu(probe_model, strided_model):
    """The CUDA backend's device ring, run eagerly on the CPU."""
    backend = CudaGraphBackend(probe_model, "fp32", device="cpu", use_graphs=False)
    _incremental_matches_run(backend, probe_model, stream(T + 32))
    strided = CudaGraphBackend(strided_model, "fp32", device="cpu", use_graphs=False)
    _incremental_matches_run(strided, strided_model, stream(strided_model.span + 32))
    np.testing.assert_allclose(
        backend.run(probe_window(probe_model))[0],
        probe_model.predict(probe_window(probe_model)[0]),
        atol=1e-5,
    )


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_cuda_graphs_agree_with_torch(probe_model, precision):
    backend = build_backend(probe_model, "cuda", precision, device="cuda")
    assert backend.use_graphs and len(backend._graphs) == T
    parity = check_parity(backend, probe_model)
    if precision == "fp32":
        assert parity.ok, str(parity)
        _incremental_matches_run(backend, probe_model, stream(T + 32))
    else:
        # bf16 rounding alone can miss the 1 % parity bar: on an H200 (2026-11-26) the
        # random probe model's bf16 graphs were 1.31 % of peak off, and auto selection
        # then keeps fp32. 5 % catches a broken bf16 path (wrong ring, wrong scaling).
        assert parity.max_abs_err_kpa <= 0.05 * max(parity.peak_kpa, 4.0), str(parity)
    backend.close()


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
def test_predictor_on_cuda_matches_cpu(probe_model):
    predictor = PressurePredictor.from_checkpoint(probe_model, "cuda", "fp32")
    frames = stream(T + 5)
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


def test_bad_backend_input(probe_model):
    backend = TorchBackend(probe_model)
    with pytest.raises(ValueError, match=r"window: expected \(1, 15, 64, 64, 3\) uint8"):
        backend.run(np.zeros((1, T, 32, 32, 3), np.uint8))


def test_one_input_path(strided_model, monkeypatch):
    """The streaming torch runtime and PressureModel.predict both take the frame stride, the
    normalisation and the output scale from FramesToPressure: change one there and both
    follow, and still agree."""
    from beadsight.model import FramesToPressure

    shared, strided_model = strided_model, PressureModel.create(strided_model.meta)
    strided_model.module.load_state_dict(shared.module.state_dict())  # patched below, not shared
    span = strided_model.span
    frames = stream(span + 12, seed=4)

    def stream_matches(backend: TorchBackend) -> list[np.ndarray]:
        maps = []
        for end in range(span - 1, len(frames)):
            window = frames[end - span + 1 : end + 1]
            got = backend.run_incremental(window[None], span if end == span - 1 else 1)[0]
            np.testing.assert_allclose(got, strided_model.predict(window), atol=1e-5, rtol=0)
            maps.append(got)
        return maps

    before = stream_matches(TorchBackend(strided_model))
    # the network sees the frames newest first: a change made in one place only
    monkeypatch.setattr(FramesToPressure, "seen", lambda self, w: w.flip(1)[:, ::3])
    monkeypatch.setattr(strided_model.module, "output_scale_kpa", torch.tensor(20.0))
    after = stream_matches(TorchBackend(strided_model))
    assert all(np.abs(a - 2 * b).max() > 1e-3 for a, b in zip(after, before, strict=True))


def test_openvino_runtimes_closed_in_order_leave_python_signal_handlers_working():
    """Two OpenVINO runtimes closed in the order they were made (auto selection drops its
    candidates so), then a signal with a Python handler, as Ctrl-C has: the process used to
    die of SIGSEGV (each CPU plugin puts back the alternate signal stack it found, the last
    one put back was a freed plugin's). Then a child that ends while the interpreter exits,
    with a SIGCHLD handler as torch's DataLoader installs: that one died silently at exit
    (rc 139, no faulthandler output: faulthandler's handler needs the same stack). In a
    child, so that a crash fails only this test."""
    proc = run_isolated(
        """
        import atexit, gc, os, signal, subprocess, time
        from beadsight.assets import shipped_model_path
        from beadsight.checkpoint import load_checkpoint
        from beadsight.inference.select import build_backend
        model = load_checkpoint(shipped_model_path())
        first = build_backend(model, "openvino", "fp32", cache_dir=None)
        second = build_backend(model, "openvino", "fp32", cache_dir=None)
        first.close(); del first; gc.collect()
        second.close(); del second; gc.collect()
        handled = []
        signal.signal(signal.SIGUSR1, lambda *_: handled.append(True))
        os.kill(os.getpid(), signal.SIGUSR1)
        print("handled", handled)
        signal.signal(signal.SIGCHLD, lambda *_: None)
        subprocess.Popen(["sleep", "0.2"])
        atexit.register(time.sleep, 0.5)  # the child ends while the interpreter exits
        """
    )
    assert proc.returncode == 0 and "handled [True]" in proc.stdout, proc.stderr


@pytest.mark.parametrize("fixture", ["rest_model", "rest_norm_model"])
def test_plane_ring_of_a_rest_referenced_model(fixture, request):
    """Strided, rest-referenced (contrast-normalised too): streamed through OpenVINO's plane
    ring with a rest image that changes mid-stream (the ring's planes are recomputed) and a
    gap of 3 frames, every reading is the module's on the same rest image and window."""
    model = request.getfixturevalue(fixture)
    backend = build_backend(model, "openvino", "fp32", cache_dir=None)
    span, frames = model.span, stream(model.span + 20, seed=5)
    rests = [stream(1, seed=21)[0], stream(1, seed=22)[0]]
    end, step = span - 1, span
    while end < len(frames):
        rest = rests[int(end >= span + 9)]
        window = frames[None, end - span + 1 : end + 1]
        got = backend.run_incremental(np.ascontiguousarray(window), step, rest)
        expected = model.predict(np.concatenate([rest[None], window[0]]))
        np.testing.assert_allclose(got[0], expected, atol=1e-4, rtol=0)
        step = 3 if end == span + 4 else 1
        end += step
    backend.close()


def test_plane_ring_refuses_a_module_whose_frame_planes_are_not_affine(probe_model, monkeypatch):
    """The ring applies the per-channel affine map it reads off the module; a module whose
    normalisation is not of that form is refused rather than run wrongly."""
    from beadsight.inference.planes import PlaneRing
    from beadsight.model import FramesToPressure

    PlaneRing(probe_model.module, probe_model.image_size)  # the shipped steps are affine
    normalize = FramesToPressure.normalize_frames
    monkeypatch.setattr(
        FramesToPressure, "normalize_frames", lambda self, f: normalize(self, f).square()
    )
    with pytest.raises(ValueError, match="not affine per colour channel"):
        PlaneRing(probe_model.module, probe_model.image_size)
