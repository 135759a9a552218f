"""Inference backends: one interface over torch, torch.compile, ONNX Runtime, OpenVINO, CUDA.

Every backend runs the whole :class:`~beadsight.model.FramesToPressure` module
(normalisation included) and has the same numpy interface::

    backend.run(window)  # (1, T, S, S, 3) uint8 RGB, oldest first -> (1, S, S) float32 kPa

The returned array belongs to the caller. :meth:`Backend.run_incremental` is
the streaming form used by :class:`~beadsight.inference.predictor.PressurePredictor`: it
is told how many frames at the end of the window are new since the previous
call, so backends that keep state (frames already normalised, frames already on
the GPU) only process those.

=========  ===========================================================  ==========
name       what runs                                                    precisions
=========  ===========================================================  ==========
torch      eager PyTorch under ``inference_mode``; keeps a ring of      fp32, bf16
           normalised frames so each frame is normalised once            (autocast)
compile    AOTInductor: ``torch.export`` + inductor with freezing,       fp32
           compiled once per checkpoint and machine and cached as a
           ``.pt2`` package in ``cache_dir`` (first build: minutes)
onnx       ONNX Runtime, CPU execution provider                          fp32
openvino   OpenVINO on the CPU with an explicit                          fp32, bf16
           ``INFERENCE_PRECISION_HINT``, ``INFERENCE_NUM_THREADS`` and   (bf16 where
           the LATENCY performance hint                                  the CPU has it)
cuda       PyTorch on a CUDA device with CUDA graphs (one graph per     fp32, bf16
           ring-buffer position, so only the newest frame is copied in)
=========  ===========================================================  ==========

Parity: :func:`create_backend` (and so the predictor) refuses a backend whose
output on the probe windows (:func:`probe_windows`) differs from fp32 torch by more
than 1 % of ``max(peak, PARITY_FLOOR_KPA)`` (:data:`PARITY_TOLERANCE`). The
floor, the pressure of the 50 g contact force spread over the finger (~4 kPa),
keeps the check meaningful when the probe's map is nearly empty (an untrained or
unlucky model): errors are then judged against a contact-sized pressure.

``backend="auto"`` (:func:`select_backend`) builds each candidate available
here, drops those that fail parity, times the rest on the probe and keeps the
fastest. A bf16 candidate must stay within half the bound
(:data:`AUTO_REDUCED_PRECISION_MARGIN`): the probes cannot cover every input,
and reduced-precision error varies with the input more than fp32 rounding does. The decision is cached per checkpoint fingerprint and machine in
``cache_dir/backend-choice.json``; on a cache hit only the chosen backend is
built (and parity-checked again). ``compile`` is not an auto candidate while
OpenVINO or ONNX Runtime is installed (its first build takes minutes); name it
explicitly.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import logging
import os
import platform
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from beadsight.checkpoint import PressureModel
from beadsight.config import ConfigError, ContactThresholds, SensorGeometry
from beadsight.errors import BeadSightError
from beadsight.geometry import disk_pressure_kpa
from beadsight.inference.config import BACKENDS, PRECISIONS

log = logging.getLogger(__name__)

CPU_AUTO_ORDER = (("openvino", "bf16"), ("openvino", "fp32"), ("onnx", "fp32"), ("torch", "fp32"))
CPU_FALLBACK_ORDER = (("compile", "fp32"), ("torch", "fp32"))  # without OpenVINO/ONNX Runtime
CUDA_AUTO_ORDER = (("cuda", "bf16"), ("cuda", "fp32"))
AUTO_WARMUP_RUNS = 2  # untimed runs before timing a candidate
AUTO_TIMED_RUNS = 5  # timed runs per candidate; the median decides
AUTO_REDUCED_PRECISION_MARGIN = 0.5  # auto takes bf16 only within half the parity bound
CHOICE_FILE = "backend-choice.json"
PROBE_SEED = 0
PROBE_TEXTURE_STD = 1.5  # probe background contrast, in units of the pixel std
PROBE_DEPTH_STD = 2.0  # darkening under the probe's finger at full press, in pixel stds
PARITY_FLOOR_KPA = float(disk_pressure_kpa(ContactThresholds().contact_n, SensorGeometry()))


class BackendError(BeadSightError):
    """A backend cannot be used for this checkpoint (unavailable, or it disagrees)."""


class BackendUnavailableError(BackendError):
    """The backend or precision is not installed or not supported by this hardware."""


class ParityError(BackendError):
    """The backend's output differs from fp32 torch by more than the tolerance."""


def default_cache_dir() -> Path:
    """``~/.cache/beadsight``: exported models, compiled packages, auto decisions."""
    return Path.home() / ".cache" / "beadsight"


def default_threads() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


# --- parity -------------------------------------------------------------------------
@dataclass(frozen=True)
class ParityTolerance:
    """Allowed max abs error: ``max(abs_kpa, fraction * max(peak_kpa, floor_kpa))``."""

    fraction: float = 0.01  # 1 % of the map's peak
    floor_kpa: float = PARITY_FLOOR_KPA  # peak used when the map's own peak is smaller
    abs_kpa: float = 0.0  # never stricter than this

    def tolerance_kpa(self, peak_kpa: float) -> float:
        return max(self.abs_kpa, self.fraction * max(float(peak_kpa), self.floor_kpa))


PARITY_TOLERANCE = ParityTolerance()


@dataclass(frozen=True)
class ParityResult:
    """Max abs error of a backend against fp32 torch on one window."""

    backend: str
    max_abs_err_kpa: float
    peak_kpa: float
    tolerance_kpa: float

    @property
    def ok(self) -> bool:
        return bool(self.max_abs_err_kpa <= self.tolerance_kpa)

    @property
    def max_abs_err_pct(self) -> float:
        """Error in % of the peak the tolerance uses (``max(peak, floor)``)."""
        scale = max(self.peak_kpa, PARITY_TOLERANCE.floor_kpa)
        return 100.0 * self.max_abs_err_kpa / scale

    def __str__(self) -> str:
        return (
            f"{self.backend}: max abs error {self.max_abs_err_kpa:.3g} kPa "
            f"({self.max_abs_err_pct:.3g} % of max(peak {self.peak_kpa:.3g}, floor "
            f"{PARITY_TOLERANCE.floor_kpa:.3g}) kPa; allowed {self.tolerance_kpa:.3g} kPa)"
        )


def _press_probe(
    model: PressureModel, rng: np.random.Generator, centre_px: tuple[float, float]
) -> np.ndarray:
    """A textured window with a dark disk deepening over time, like a finger press."""
    t, s = model.window, model.image_size
    mean = np.asarray(model.meta.pixel_mean, dtype=np.float64)
    std = np.asarray(model.meta.pixel_std, dtype=np.float64)
    if model.meta.channel_order == "BGR":
        mean, std = mean[::-1], std[::-1]
    texture = rng.normal(0.0, PROBE_TEXTURE_STD, size=(s, s, 1)) * std + mean
    rows, cols = np.mgrid[0:s, 0:s] + 0.5
    radius = model.geometry.finger_radius_mm / model.geometry.mm_per_px
    disk = np.clip(radius - np.hypot(rows - centre_px[0], cols - centre_px[1]) + 0.5, 0, 1)
    depth = np.linspace(0.0, 1.0, t)[:, None, None, None]
    frames = texture[None] - depth * disk[None, :, :, None] * PROBE_DEPTH_STD * std
    frames = frames + rng.normal(0.0, 1.0, size=frames.shape)
    return np.clip(np.rint(frames), 0, 255).astype(np.uint8)


def probe_windows(model: PressureModel, seed: int = PROBE_SEED) -> np.ndarray:
    """(K, T, S, S, 3) uint8 RGB windows the parity check runs on.

    A synthetic press (textured frames at the checkpoint's pixel statistics with
    a darkening finger disk, at the centre and off-centre) and uniform noise:
    maps with pressure in them for a trained model, and inputs far from the
    training data that stress a reduced precision.
    """
    rng = np.random.default_rng(seed)
    t, s = model.window, model.image_size
    offset = s / 4
    return np.stack(
        [
            _press_probe(model, rng, (s / 2, s / 2)),
            _press_probe(model, rng, (s / 2 - offset, s / 2 + offset)),
            rng.integers(0, 256, size=(t, s, s, 3), dtype=np.uint8),
        ]
    )


def probe_window(model: PressureModel, seed: int = PROBE_SEED) -> np.ndarray:
    """The (1, T, S, S, 3) probe window whose fp32 torch map peaks highest."""
    windows = probe_windows(model, seed)
    peaks = model.predict(windows, batch_size=1).max(axis=(1, 2))
    return windows[int(np.argmax(peaks))][None]


def check_parity(
    backend: Backend,
    model: PressureModel,
    windows: np.ndarray | None = None,
    expected: np.ndarray | None = None,
    tolerance: ParityTolerance | None = None,
) -> ParityResult:
    """Compare ``backend.run`` with fp32 torch (``model.predict``), window by window.

    windows: (K, T, S, S, 3) uint8 RGB (default :func:`probe_windows`); expected:
    their (K, S, S) fp32 maps if already computed. Each window is judged against
    its own peak; the result is the worst one (largest error / tolerance).
    """
    windows = probe_windows(model) if windows is None else windows
    expected = model.predict(windows, batch_size=1) if expected is None else expected
    tolerance = tolerance or PARITY_TOLERANCE
    worst: ParityResult | None = None
    for window, reference in zip(windows, expected, strict=True):
        got = backend.run(window[None])[0]
        peak = float(np.abs(reference).max())
        err = float(np.abs(got.astype(np.float64) - reference).max())
        result = ParityResult(backend.describe(), err, peak, tolerance.tolerance_kpa(peak))
        if worst is None or _ratio(result) > _ratio(worst):
            worst = result
    return worst


def _ratio(result: ParityResult) -> float:
    return result.max_abs_err_kpa / result.tolerance_kpa if result.tolerance_kpa > 0 else np.inf


# --- the interface ------------------------------------------------------------------
class Backend:
    """Runs one checkpoint's FramesToPressure on numpy windows.

    Subclasses implement :meth:`_run`; ``name`` and ``precision`` describe them.
    """

    name = "base"

    def __init__(self, model: PressureModel, precision: str = "fp32"):
        if precision not in PRECISIONS:
            raise ConfigError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self.model = model
        self.precision = precision
        self.window = model.window
        self.image_size = model.image_size
        self._shape = (1, self.window, self.image_size, self.image_size, 3)

    def describe(self) -> str:
        return f"{self.name}/{self.precision}"

    def _check(self, window: np.ndarray) -> None:
        if getattr(window, "shape", None) != self._shape or window.dtype != np.uint8:
            raise ValueError(
                f"window: expected {self._shape} uint8 RGB, got "
                f"{getattr(window, 'shape', None)} {getattr(window, 'dtype', type(window))}"
            )

    def run(self, window: np.ndarray) -> np.ndarray:
        """window: (1, T, S, S, 3) uint8 RGB, oldest first -> (1, S, S) float32 kPa."""
        self._check(window)
        return self._run(np.ascontiguousarray(window))

    def run_incremental(self, window: np.ndarray, new_frames: int) -> np.ndarray:
        """Like :meth:`run`, where only the last ``new_frames`` frames of ``window``
        differ from the previous call's window shifted by ``new_frames`` (``>= T``:
        all new). Stateless backends just call :meth:`run`."""
        return self.run(window)

    def _run(self, window: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def close(self) -> None:
        """Release the backend's resources (sessions, GPU memory)."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}>"


def _torch_module(model: PressureModel, device: torch.device) -> torch.nn.Module:
    """The model's module on ``device``; a copy if that means moving it."""
    module = model.module
    if next(module.parameters()).device != device:
        module = copy.deepcopy(module).to(device)
    return module.eval()


class TorchBackend(Backend):
    """Eager PyTorch. Streaming keeps a doubled ring of normalised frames.

    precision "bf16" runs under ``torch.autocast`` (convolutions in bf16,
    normalisation in fp32).
    """

    name = "torch"

    def __init__(
        self,
        model: PressureModel,
        precision: str = "fp32",
        device: str | torch.device | None = None,
        threads: int | None = None,
    ):
        super().__init__(model, precision)
        self.device = torch.device(device or "cpu")
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise BackendUnavailableError("torch: CUDA requested but torch.cuda is unavailable")
        if threads:
            torch.set_num_threads(int(threads))
        self.module = _torch_module(model, self.device)
        t, s = self.window, self.image_size
        self._ring = torch.zeros((1, 6 * t, s, s), dtype=torch.float32, device=self.device)
        self._head = -1  # ring slot of the newest normalised frame, in [0, T)
        m = self.module
        self._mean = m.pixel_mean.view(3, 1, 1).to(self.device)
        self._std = m.pixel_std.view(3, 1, 1).to(self.device)
        self._perm = m.channel_perm.to(self.device)

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _output(self, y: torch.Tensor) -> np.ndarray:
        return y.float().cpu().numpy().copy()

    @torch.inference_mode()
    def _run(self, window: np.ndarray) -> np.ndarray:
        x = torch.from_numpy(window).to(self.device)
        with self._autocast():
            return self._output(self.module(x))

    @torch.inference_mode()
    def _push(self, frame: np.ndarray) -> None:
        """Normalise one (S, S, 3) uint8 RGB frame into the ring (twice: slot i and i+T)."""
        t = self.window
        head = (self._head + 1) % t
        x = torch.from_numpy(frame).to(self.device).permute(2, 0, 1).index_select(0, self._perm)
        slot = self._ring[0, 3 * head : 3 * head + 3]
        torch.sub(x.to(torch.float32), self._mean, out=slot)
        slot.div_(self._std)
        self._ring[0, 3 * (head + t) : 3 * (head + t) + 3] = slot
        self._head = head

    @torch.inference_mode()
    def run_incremental(self, window: np.ndarray, new_frames: int) -> np.ndarray:
        self._check(window)
        t = self.window
        if self._head < 0:
            new_frames = t
        for k in range(t - min(int(new_frames), t), t):
            self._push(window[0, k])
        start = 3 * (self._head + 1)
        x = self._ring[:, start : start + 3 * t]  # (1, 3T, S, S), oldest first
        m = self.module
        stride = m.net.config.frame_stride
        if stride > 1:  # the frames the network sees: every stride-th, the newest included
            x = x.unflatten(1, (t, 3))[:, ::stride].flatten(1, 2)
        with self._autocast():
            return self._output(m.net(x)[:, 0] * m.output_scale_kpa)


class CompileBackend(Backend):
    """AOTInductor-compiled module (freezing on), cached on disk per checkpoint+machine."""

    name = "compile"

    def __init__(
        self,
        model: PressureModel,
        precision: str = "fp32",
        cache_dir: Path | None = None,
        threads: int | None = None,
    ):
        super().__init__(model, precision)
        if precision != "fp32":
            raise BackendUnavailableError("compile: only fp32 is supported; use openvino for bf16")
        if threads:
            torch.set_num_threads(int(threads))
        from beadsight.inference.export import model_fingerprint

        name = f"{model_fingerprint(model)[:24]}-{_machine_key()}.pt2"
        folder = Path(cache_dir) if cache_dir else Path(tempfile.mkdtemp(prefix="beadsight-"))
        path = folder / "aoti" / name
        if not path.is_file():
            self._compile(model, path)
        else:
            log.info("compile: loading cached %s", path)
        self._fn = torch._inductor.aoti_load_package(str(path))
        self.path = path

    def _compile(self, model: PressureModel, path: Path) -> None:
        import torch._inductor.config as inductor_config

        log.info("compile: building %s (AOTInductor; takes a while the first time)", path)
        path.parent.mkdir(parents=True, exist_ok=True)
        module = copy.deepcopy(model.module).to("cpu").eval()
        example = torch.zeros(self._shape, dtype=torch.uint8)
        with torch.no_grad():
            program = torch.export.export(module, (example,))
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.pt2")
        with inductor_config.patch({"freezing": True}):
            torch._inductor.aoti_compile_and_package(program, package_path=str(tmp))
        os.replace(tmp, path)

    @torch.inference_mode()
    def _run(self, window: np.ndarray) -> np.ndarray:
        return self._fn(torch.from_numpy(window)).float().numpy().copy()


def _open_onnx_session(path: Path, threads: int):
    try:
        import onnxruntime as ort
    except ImportError:
        raise BackendUnavailableError(
            "onnx: onnxruntime is not installed; `pip install beadsight[export]`"
        ) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def _exported_file(model: PressureModel, cache_dir: Path | None) -> tuple[Path, Any]:
    """An ONNX export of ``model``: cached under ``cache_dir/onnx``, else a temp dir."""
    from beadsight.inference.export import model_fingerprint, write_onnx

    if cache_dir:
        path = Path(cache_dir) / "onnx" / f"{model_fingerprint(model)[:24]}.onnx"
        if not path.is_file():
            write_onnx(model, path)
        return path, None
    tmp = tempfile.TemporaryDirectory(prefix="beadsight-")
    return write_onnx(model, Path(tmp.name) / "model.onnx"), tmp


class OnnxBackend(Backend):
    """ONNX Runtime on the CPU (fp32)."""

    name = "onnx"

    def __init__(
        self,
        model: PressureModel,
        precision: str = "fp32",
        exported_model: str | Path | None = None,
        cache_dir: Path | None = None,
        threads: int | None = None,
    ):
        super().__init__(model, precision)
        if precision != "fp32":
            raise BackendUnavailableError(
                "onnx: onnxruntime's CPU provider has no bf16 convolutions; use openvino"
            )
        self._tmp = None
        if exported_model is not None:
            path = Path(exported_model)
        else:
            path, self._tmp = _exported_file(model, cache_dir)
        self.path = path
        self.session = _open_onnx_session(path, int(threads or default_threads()))
        self._input = self.session.get_inputs()[0].name

    def _run(self, window: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self._input: window})[0]

    def close(self) -> None:
        self.session = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


def openvino_supports_bf16(core: Any = None) -> bool:
    """True when OpenVINO's CPU plugin reports native bf16 (avx512_bf16 / AMX)."""
    try:
        import openvino as ov
    except ImportError:
        return False
    core = core or ov.Core()
    return "BF16" in core.get_property("CPU", "OPTIMIZATION_CAPABILITIES")


class OpenVinoBackend(Backend):
    """OpenVINO on the CPU with explicit precision, threads and latency hint."""

    name = "openvino"

    def __init__(
        self,
        model: PressureModel,
        precision: str = "fp32",
        exported_model: str | Path | None = None,
        cache_dir: Path | None = None,
        threads: int | None = None,
    ):
        super().__init__(model, precision)
        try:
            import openvino as ov
        except ImportError:
            raise BackendUnavailableError(
                "openvino: not installed; `pip install beadsight[openvino]`"
            ) from None
        core = ov.Core()
        if precision == "bf16" and not openvino_supports_bf16(core):
            raise BackendUnavailableError("openvino: this CPU has no native bf16")
        tmp = None
        if exported_model is not None:
            ov_model = core.read_model(str(exported_model))
        else:
            path, tmp = _exported_file(model, cache_dir)
            ov_model = core.read_model(str(path))
        ov_model.reshape({ov_model.inputs[0]: list(self._shape)})
        config = {
            "INFERENCE_PRECISION_HINT": "bf16" if precision == "bf16" else "f32",
            "INFERENCE_NUM_THREADS": int(threads or default_threads()),
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,
        }
        if cache_dir:
            (Path(cache_dir) / "openvino").mkdir(parents=True, exist_ok=True)
            config["CACHE_DIR"] = str(Path(cache_dir) / "openvino")
        self.compiled = core.compile_model(ov_model, "CPU", config)
        if tmp is not None:
            tmp.cleanup()
        self.request = self.compiled.create_infer_request()
        self.config = config

    def _run(self, window: np.ndarray) -> np.ndarray:
        self.request.infer({0: window}, share_inputs=True, share_outputs=True)
        return self.request.get_output_tensor(0).data.copy()

    def close(self) -> None:
        self.request = None
        self.compiled = None


class CudaGraphBackend(Backend):
    """PyTorch on a CUDA device, replaying CUDA graphs.

    Frames live on the device in a doubled uint8 ring (slots ``i`` and ``i + T``);
    one graph per ring position runs the full module on the contiguous view
    ``ring[head + 1 : head + 1 + T]``, so streaming copies only the new frame to
    the device. ``use_graphs=False`` runs the same ring eagerly (and works on
    any torch device, which the tests use on the CPU). fp32 runs with TF32 off.
    """

    name = "cuda"

    def __init__(
        self,
        model: PressureModel,
        precision: str = "fp32",
        device: str | torch.device | None = None,
        use_graphs: bool = True,
    ):
        super().__init__(model, precision)
        self.device = torch.device(device or "cuda")
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise BackendUnavailableError("cuda: no CUDA device is available to torch")
        if precision == "bf16" and self.device.type == "cuda":
            if not torch.cuda.is_bf16_supported():
                raise BackendUnavailableError(f"cuda: {self.device} has no bf16 support")
        self.use_graphs = use_graphs and self.device.type == "cuda"
        self.module = _torch_module(model, self.device)
        t, s = self.window, self.image_size
        self._ring = torch.zeros((1, 2 * t, s, s, 3), dtype=torch.uint8, device=self.device)
        self._head = t - 1
        self._streaming = False  # True while the ring holds the stream's last T frames
        pin = self.device.type == "cuda"
        self._host_out = torch.empty((1, s, s), dtype=torch.float32, pin_memory=pin)
        self._outputs: list[torch.Tensor] = []
        self._graphs: list[Any] = []
        if self.use_graphs:
            self._capture()

    def _context(self):
        stack = contextlib.ExitStack()
        if self.device.type == "cuda":
            stack.enter_context(
                torch.backends.cudnn.flags(enabled=True, benchmark=True, allow_tf32=False)
            )
        if self.precision == "bf16":
            stack.enter_context(
                torch.autocast(self.device.type, dtype=torch.bfloat16, cache_enabled=False)
            )
        return stack

    def _view(self, head: int) -> torch.Tensor:
        return self._ring[:, head + 1 : head + 1 + self.window]

    def _forward(self, head: int) -> torch.Tensor:
        with self._context():
            return self.module(self._view(head)).float()

    @torch.inference_mode()
    def _capture(self) -> None:
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(3):  # warm-up: cuDNN algorithm choice, allocator
                self._forward(self.window - 1)
        torch.cuda.current_stream(self.device).wait_stream(side)
        pool = None
        for head in range(self.window):
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph, pool=pool):
                out = self._forward(head)
            pool = graph.pool()
            self._graphs.append(graph)
            self._outputs.append(out)

    def _compute(self) -> np.ndarray:
        if self.use_graphs:
            self._graphs[self._head].replay()
            out = self._outputs[self._head]
        else:
            out = self._forward(self._head)
        self._host_out.copy_(out, non_blocking=self.device.type == "cuda")
        if self.device.type == "cuda":
            torch.cuda.current_stream(self.device).synchronize()
        return self._host_out.numpy().copy()

    def _push(self, frames: np.ndarray) -> None:
        """Copy (N, S, S, 3) uint8 frames into the ring, oldest first."""
        t = self.window
        for frame in frames[-t:]:
            head = (self._head + 1) % t
            x = torch.from_numpy(frame).to(self.device, non_blocking=False)
            self._ring[0, head] = x
            self._ring[0, head + t] = x
            self._head = head

    def _load(self, window: np.ndarray) -> None:
        """Copy a whole (1, T, S, S, 3) window into both halves of the ring."""
        t = self.window
        x = torch.from_numpy(window[0]).to(self.device)
        self._ring[0, :t] = x
        self._ring[0, t:] = x
        self._head = t - 1

    @torch.inference_mode()
    def _run(self, window: np.ndarray) -> np.ndarray:
        self._load(window)
        self._streaming = False  # the ring no longer holds the stream's frames
        return self._compute()

    @torch.inference_mode()
    def run_incremental(self, window: np.ndarray, new_frames: int) -> np.ndarray:
        self._check(window)
        if new_frames >= self.window or not self._streaming:
            self._load(np.ascontiguousarray(window))
        elif new_frames > 0:
            self._push(window[0, self.window - int(new_frames) :])
        self._streaming = True
        return self._compute()

    def close(self) -> None:
        self._graphs.clear()
        self._outputs.clear()
        self._ring = None


# --- construction -------------------------------------------------------------------
def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _machine_key() -> str:
    """Short hash of what makes timings and compiled code machine-specific."""
    parts = [platform.machine(), _cpu_name(), str(default_threads()), torch.__version__]
    for name in ("onnxruntime", "openvino"):
        try:
            parts.append(f"{name}={__import__(name).__version__}")
        except ImportError:
            parts.append(f"{name}=none")
    try:
        import openvino as ov

        parts.append(",".join(ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")))
    except ImportError:
        pass
    if torch.cuda.is_available():
        parts.append(torch.cuda.get_device_name(0))
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]


def _wants_cuda(device: str | torch.device | None) -> bool:
    if device is None:
        return torch.cuda.is_available()
    return torch.device(device).type == "cuda"


def build_backend(
    model: PressureModel,
    name: str,
    precision: str = "fp32",
    device: str | torch.device | None = None,
    exported_model: str | Path | None = None,
    cache_dir: Path | None = None,
    threads: int | None = None,
) -> Backend:
    """Construct backend ``name`` without any parity check (see :func:`create_backend`)."""
    if name not in BACKENDS:
        raise ConfigError(f"backend must be 'auto' or one of {BACKENDS}, got {name!r}")
    if exported_model is not None and name not in ("onnx", "openvino"):
        raise ConfigError(f"exported_model needs backend 'onnx' or 'openvino', not {name!r}")
    if name == "torch":
        return TorchBackend(model, precision, device=device, threads=threads)
    if name == "compile":
        return CompileBackend(model, precision, cache_dir=cache_dir, threads=threads)
    if name == "onnx":
        return OnnxBackend(model, precision, exported_model, cache_dir, threads)
    if name == "openvino":
        return OpenVinoBackend(model, precision, exported_model, cache_dir, threads)
    return CudaGraphBackend(model, precision, device=device)


def time_backend(backend: Backend, window: np.ndarray, runs: int = AUTO_TIMED_RUNS) -> float:
    """Median seconds per ``backend.run(window)`` after :data:`AUTO_WARMUP_RUNS` warm-ups."""
    for _ in range(AUTO_WARMUP_RUNS):
        backend.run(window)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        backend.run(window)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _choice_key(model: PressureModel, precision: str, device: Any) -> str:
    from beadsight.inference.export import model_fingerprint

    return f"{model_fingerprint(model)[:24]}|{_machine_key()}|{precision}|{device}"


def _read_choices(cache_dir: Path | None) -> dict[str, Any]:
    if not cache_dir:
        return {}
    try:
        return json.loads((Path(cache_dir) / CHOICE_FILE).read_text())
    except (OSError, ValueError):
        return {}


def _write_choice(cache_dir: Path | None, key: str, choice: dict[str, Any]) -> None:
    if not cache_dir:
        return
    folder = Path(cache_dir)
    folder.mkdir(parents=True, exist_ok=True)
    choices = _read_choices(folder)
    choices[key] = choice
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(choices, f, indent=1, sort_keys=True)
    os.replace(tmp, folder / CHOICE_FILE)


def auto_candidates(precision: str = "auto", device: Any = None) -> list[tuple[str, str]]:
    """(backend, precision) pairs ``auto`` tries here, expected-fastest first."""
    if _wants_cuda(device):
        order = list(CUDA_AUTO_ORDER)
    else:
        have_fast = any(_importable(m) for m in ("openvino", "onnxruntime"))
        order = list(CPU_AUTO_ORDER if have_fast else CPU_FALLBACK_ORDER)
    if precision != "auto":
        order = [c for c in order if c[1] == precision]
    return order


def _importable(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


@dataclass(frozen=True)
class Candidate:
    """One backend tried by :func:`select_backend`."""

    backend: str
    precision: str
    seconds: float | None  # median run time on the probe; None if unusable
    note: str  # parity result or why it was skipped
    err_pct: float | None = None  # worst parity error, % of max(peak, floor)


def select_backend(
    model: PressureModel,
    precision: str = "auto",
    device: str | torch.device | None = None,
    cache_dir: Path | None = None,
    threads: int | None = None,
    candidates: list[tuple[str, str]] | None = None,
) -> Backend:
    """The fastest candidate whose output agrees with fp32 torch (see module docs).

    The chosen backend has ``.selection`` (list of :class:`Candidate`) and
    ``.parity`` (:class:`ParityResult`) attributes.
    """
    if precision not in ("auto", *PRECISIONS):
        raise ConfigError(f"precision must be 'auto' or one of {PRECISIONS}, got {precision!r}")
    todo = candidates or auto_candidates(precision, device)
    if not todo:
        raise BackendUnavailableError(f"auto: no backend runs {precision} on this machine")
    windows = probe_windows(model)
    expected = model.predict(windows, batch_size=1)
    timing_window = windows[int(np.argmax(expected.max(axis=(1, 2))))][None]
    key = _choice_key(model, precision, device)
    cached = _read_choices(cache_dir).get(key)
    if cached and (cached["backend"], cached["precision"]) in todo:
        backend = _try_candidate(
            model,
            cached["backend"],
            cached["precision"],
            device,
            cache_dir,
            threads,
            windows,
            expected,
        )
        if isinstance(backend, Backend):
            log.info("auto: %s (cached decision)", backend.describe())
            known = set(Candidate.__dataclass_fields__)
            backend.selection = [
                Candidate(**{k: v for k, v in c.items() if k in known})
                for c in cached.get("candidates", [])
            ]
            return backend
    best: Backend | None = None
    best_time = float("inf")
    tried: list[Candidate] = []
    for name, prec in todo:
        backend = _try_candidate(model, name, prec, device, cache_dir, threads, windows, expected)
        if not isinstance(backend, Backend):
            tried.append(Candidate(name, prec, None, backend))
            continue
        seconds = time_backend(backend, timing_window)
        parity = backend.parity
        tried.append(Candidate(name, prec, seconds, str(parity), parity.max_abs_err_pct))
        log.info("auto: %s %.1f ms", backend.describe(), seconds * 1e3)
        if seconds < best_time:
            if best is not None:
                best.close()
            best, best_time = backend, seconds
        else:
            backend.close()
    if best is None:
        raise BackendUnavailableError(
            "auto: no backend both runs here and agrees with torch: "
            + "; ".join(f"{c.backend}/{c.precision}: {c.note}" for c in tried)
        )
    best.selection = tried
    _write_choice(
        cache_dir,
        key,
        {
            "backend": best.name,
            "precision": best.precision,
            "candidates": [c.__dict__ for c in tried],
            "created_unix_s": time.time(),
        },
    )
    log.info("auto: chose %s", best.describe())
    return best


def _try_candidate(model, name, precision, device, cache_dir, threads, windows, expected):
    """A parity-checked backend, or a string saying why it cannot be used."""
    try:
        backend = build_backend(model, name, precision, device, None, cache_dir, threads)
    except (BackendUnavailableError, ImportError, RuntimeError) as e:
        log.debug("auto: %s/%s unavailable: %s", name, precision, e)
        return f"unavailable ({e})"
    tolerance = PARITY_TOLERANCE
    if precision != "fp32":  # probes cannot cover every input: demand a margin
        tolerance = replace(tolerance, fraction=tolerance.fraction * AUTO_REDUCED_PRECISION_MARGIN)
    parity = check_parity(backend, model, windows, expected, tolerance)
    if not parity.ok:
        backend.close()
        log.info("auto: %s rejected: %s", backend.describe(), parity)
        return f"rejected, {parity}"
    backend.parity = parity
    return backend


def create_backend(
    model: PressureModel,
    backend: str = "auto",
    precision: str = "auto",
    device: str | torch.device | None = None,
    exported_model: str | Path | None = None,
    cache_dir: Path | None | str = "default",
    threads: int | None = None,
    check: bool = True,
) -> Backend:
    """A ready backend for ``model``; refused with :class:`ParityError` if it disagrees.

    backend: "auto" or one of :data:`BACKENDS`. precision: "fp32", "bf16", or
    "auto" (auto selection chooses; a named backend uses fp32, or the precision an
    exported file was made for). exported_model: a ``.onnx`` or OpenVINO ``.xml``
    file made by :func:`beadsight.inference.export.export_model` from this checkpoint
    (refused with :class:`beadsight.inference.export.ExportError` if it was made from another);
    with backend "auto" the format picks the backend. cache_dir: "default" ->
    :func:`default_cache_dir`, None -> no disk cache.
    """
    cache = default_cache_dir() if cache_dir == "default" else cache_dir
    cache = Path(cache) if cache else None
    if exported_model is not None:
        return open_exported(exported_model, model, backend, precision, threads, check)
    if backend == "auto":
        return select_backend(model, precision, device, cache, threads)
    if precision not in ("auto", *PRECISIONS):
        raise ConfigError(f"precision must be 'auto' or one of {PRECISIONS}, got {precision!r}")
    prec = "fp32" if precision == "auto" else precision
    result = build_backend(model, backend, prec, device, None, cache, threads)
    if check and not (backend == "torch" and prec == "fp32"):
        _require_parity(result, model)
    return result


def _require_parity(backend: Backend, model: PressureModel) -> None:
    parity = check_parity(backend, model)
    backend.parity = parity
    if not parity.ok:
        backend.close()
        raise ParityError(
            f"backend {backend.describe()} disagrees with fp32 torch for checkpoint "
            f"{model.source}: {parity}; choose another backend or precision"
        )


def open_exported(
    path: str | Path,
    model: PressureModel,
    backend: str = "auto",
    precision: str = "auto",
    threads: int | None = None,
    check: bool = True,
) -> Backend:
    """Run an exported ``.onnx`` / ``.xml`` file, after checking it belongs to ``model``."""
    from beadsight.inference.export import PRECISION_KEY, check_exported_matches

    path = Path(path)
    meta = check_exported_matches(path, model)
    if backend == "auto":
        backend = "openvino" if path.suffix == ".xml" else "onnx"
    if backend not in ("onnx", "openvino"):
        raise ConfigError(f"{path}: exported models run on 'onnx' or 'openvino', not {backend!r}")
    if backend == "onnx" and path.suffix != ".onnx":
        raise ConfigError(f"{path}: onnxruntime runs .onnx files; use backend 'openvino'")
    prec = meta.get(PRECISION_KEY, "fp32") if precision == "auto" else precision
    result = build_backend(model, backend, prec, None, path, None, threads)
    if check:
        _require_parity(result, model)
    return result
