"""Inference runtimes: one interface over torch, ONNX Runtime, OpenVINO, CUDA.

Every runtime ("backend") runs a :class:`~beadsight.model.FramesToPressure` module
(input handling included) and has the same numpy interface::

    backend.run(images)  # (1, inputs, S, S, 3) uint8 RGB -> (1, S, S) float32 kPa
    # images: a rest-referenced model's rest image first, then the window oldest first

The returned array belongs to the caller. :meth:`Backend.run_incremental` is the
streaming form used by :class:`~beadsight.inference.predictor.PressurePredictor`: it is
told how many frames at the end of the window are new since the previous call, so
runtimes that keep state (frames already normalised, frames already on the GPU) only
process those. The torch runtimes do so through the module's own steps
(``normalize_frames``, ``stack``, ``pressure``), so input handling is written once; the
ONNX Runtime and OpenVINO runtimes built from a checkpoint run its network alone on
planes computed per frame by the same steps (:mod:`beadsight.inference.planes`).

=========  ===========================================================  ==========
name       what runs                                                    precisions
=========  ===========================================================  ==========
torch      eager PyTorch under ``inference_mode``; keeps a ring of      fp32, bf16
           normalised frames so each frame is normalised once            (autocast)
onnx       ONNX Runtime, CPU execution provider; streaming keeps a       fp32
           ring of each frame's input planes
openvino   OpenVINO on the CPU with an explicit                          fp32, bf16
           ``INFERENCE_PRECISION_HINT``, ``INFERENCE_NUM_THREADS`` and   (bf16 where
           the LATENCY performance hint; the same ring                   the CPU has it)
cuda       PyTorch on a CUDA device with CUDA graphs (one graph per     fp32, bf16
           ring-buffer position, so only the newest frame is copied in)
=========  ===========================================================  ==========

The ``int8`` runtime (OpenVINO after NNCF quantization) is
:mod:`beadsight.inference.int8`. :func:`beadsight.inference.select.build_backend`
constructs any of them by name, without checks; parity
(:mod:`beadsight.inference.parity`, :mod:`beadsight.inference.metric_parity`) and the
choice of a backend (:mod:`beadsight.inference.select`) build on it.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from beadsight.checkpoint import PressureModel
from beadsight.inference.backend import (
    BACKENDS,
    PRECISIONS,
    Backend,
    BackendError,
    BackendUnavailableError,
)
from beadsight.inference.export_format import model_fingerprint
from beadsight.inference.machine import (
    default_threads,
    import_openvino,
    openvino_signal_stack_kept,
)
from beadsight.inference.planes import GRAPH_VERSION, PlaneRing, ring_inputs, write_network_onnx

log = logging.getLogger(__name__)

__all__ = [  # the interface is re-exported: runtimes are used through it
    "BACKENDS",
    "PRECISIONS",
    "Backend",
    "BackendError",
    "BackendUnavailableError",
    "CudaGraphBackend",
    "OnnxBackend",
    "OpenVinoBackend",
    "TorchBackend",
    "openvino_supports_bf16",
]


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
    batched = True

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
        n, s = self.span, self.image_size
        # normalised frames, each twice (slots i and i + span): (1, 2 span, 3, S, S)
        self._ring = torch.zeros((1, 2 * n, 3, s, s), dtype=torch.float32, device=self.device)
        self._head = -1  # ring slot of the newest normalised frame, in [0, span)
        self._rest: np.ndarray | None = None  # the rest image last normalised ...
        self._rest_x: torch.Tensor | None = None  # ... and it normalised: (1, 1, 3, S, S)

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

    def _push(self, frame: np.ndarray) -> None:
        """Normalise one (S, S, 3) uint8 RGB frame into the ring (slots i and i + span)."""
        n = self.span
        head = (self._head + 1) % n
        x = torch.from_numpy(frame).to(self.device)[None, None]  # (1, 1, S, S, 3)
        self._ring[:, head] = self.module.normalize_frames(x)[:, 0]
        self._ring[:, head + n] = self._ring[:, head]
        self._head = head

    def _normalized_rest(self, rest: np.ndarray | None) -> torch.Tensor | None:
        """The rest image normalised, redone only when it changes."""
        if rest is None:
            return None
        if self._rest is not rest and not np.array_equal(self._rest, rest):
            x = torch.from_numpy(np.array(rest, order="C")).to(self.device)[None, None]
            self._rest_x = self.module.normalize_frames(x)  # (1, 1, 3, S, S)
        self._rest = rest
        return self._rest_x

    @torch.inference_mode()
    def run_incremental(
        self, window: np.ndarray, new_frames: int, rest: np.ndarray | None = None
    ) -> np.ndarray:
        n = self.span
        self._check(window, (1, n, *self._shape[2:]))
        self._check_rest(rest)
        if self._head < 0:
            new_frames = n
        for k in range(n - min(int(new_frames), n), n):
            self._push(window[0, k])
        view = self._ring[:, self._head + 1 : self._head + 1 + n]  # (1, span, 3, S, S)
        x = self.module.stack_window(view, self._normalized_rest(rest))
        with self._autocast():
            return self._output(self.module.pressure(x))


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


def _network_file(model: PressureModel, cache_dir: Path | None) -> tuple[Path, Any]:
    """The model's network on ring-order planes as ONNX (:mod:`beadsight.inference.planes`):
    cached under ``cache_dir/onnx``, else in a temp dir."""
    name = f"{model_fingerprint(model)[:24]}-{GRAPH_VERSION}.onnx"
    if cache_dir:
        path = Path(cache_dir) / "onnx" / name
        if not path.is_file():
            write_network_onnx(model.module, model.image_size, path)
        return path, None
    tmp = tempfile.TemporaryDirectory(prefix="beadsight-")
    return write_network_onnx(model.module, model.image_size, Path(tmp.name) / name), tmp


class _ModelFileBackend(Backend):
    """A runtime that runs an ONNX file on the CPU. Built from the checkpoint, it runs the
    network alone on float32 planes (cached under ``cache_dir/onnx``, else in a temp dir
    removed once loaded), and streaming computes each frame's planes once
    (:class:`~beadsight.inference.planes.PlaneRing`); given ``exported_model``, it runs
    that file (the whole module: uint8 windows in). Subclasses load the file in
    :meth:`_load` and run it in :meth:`_infer`."""

    def __init__(
        self,
        model: PressureModel,
        precision: str = "fp32",
        exported_model: str | Path | None = None,
        cache_dir: Path | None = None,
        threads: int | None = None,
    ):
        super().__init__(model, precision)
        self._check_available()
        if exported_model:
            self.planes, self.input_shape = None, self._shape
            path, tmp = Path(exported_model), None
        else:
            self.planes = PlaneRing(model.module, self.image_size)
            self.input_shape = (1, self.planes.channels, self.image_size, self.image_size)
            path, tmp = _network_file(model, cache_dir)
        try:
            self._load(path, int(threads or default_threads()), cache_dir)
        finally:
            if tmp is not None:
                tmp.cleanup()
        self.path = path

    def _check_available(self) -> None:
        """Raise BackendUnavailableError before any export when this runtime cannot run."""

    def _load(self, path: Path, threads: int, cache_dir: Path | None) -> None:
        raise NotImplementedError

    def _infer(self, inputs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _run(self, images: np.ndarray) -> np.ndarray:
        if self.planes is None:
            return self._infer(images)
        planes = ring_inputs(self.model.module, images)
        quantizer = self.planes.quantizer
        return self._infer(planes if quantizer is None else quantizer(planes))

    def run_incremental(
        self, window: np.ndarray, new_frames: int, rest: np.ndarray | None = None
    ) -> np.ndarray:
        if self.planes is None:
            return super().run_incremental(window, new_frames, rest)
        self._check(window, (1, self.span, *self._shape[2:]))
        self._check_rest(rest)
        return self._infer(self.planes.update(window, new_frames, rest))


class OnnxBackend(_ModelFileBackend):
    """ONNX Runtime on the CPU (fp32)."""

    name = "onnx"
    batched = True  # exported graphs have a dynamic batch axis

    def _check_available(self) -> None:
        if self.precision != "fp32":
            raise BackendUnavailableError(
                "onnx: onnxruntime's CPU provider has no bf16 convolutions; use openvino"
            )

    def _load(self, path: Path, threads: int, cache_dir: Path | None) -> None:
        self.session = _open_onnx_session(path, threads)
        self._input = self.session.get_inputs()[0].name

    def _infer(self, inputs: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self._input: inputs})[0]

    def close(self) -> None:
        self.session = None


def openvino_supports_bf16(core: Any = None) -> bool:
    """True when OpenVINO's CPU plugin reports native bf16 (avx512_bf16 / AMX)."""
    try:
        ov = import_openvino()
    except ImportError:
        return False
    with openvino_signal_stack_kept():
        core = core or ov.Core()
        return "BF16" in core.get_property("CPU", "OPTIMIZATION_CAPABILITIES")


class OpenVinoBackend(_ModelFileBackend):
    """OpenVINO on the CPU with explicit precision, threads and latency hint."""

    name = "openvino"

    def _load(self, path: Path, threads: int, cache_dir: Path | None) -> None:
        try:
            ov = import_openvino()
        except ImportError:
            raise BackendUnavailableError(
                "openvino: not installed; `pip install beadsight[openvino]`"
            ) from None
        with openvino_signal_stack_kept():  # the CPU plugin loads here
            core = ov.Core()
            if self.precision == "bf16" and not openvino_supports_bf16(core):
                raise BackendUnavailableError("openvino: this CPU has no native bf16")
            ov_model = core.read_model(str(path))
            ov_model.reshape({ov_model.inputs[0]: list(self.input_shape)})
            config = {
                "INFERENCE_PRECISION_HINT": "bf16" if self.precision == "bf16" else "f32",
                "INFERENCE_NUM_THREADS": threads,
                "PERFORMANCE_HINT": "LATENCY",
                "NUM_STREAMS": 1,
            }
            if cache_dir:
                (Path(cache_dir) / "openvino").mkdir(parents=True, exist_ok=True)
                config["CACHE_DIR"] = str(Path(cache_dir) / "openvino")
            self.compiled = core.compile_model(ov_model, "CPU", config)
            self.request = self.compiled.create_infer_request()
            self.config = config

    def _infer(self, inputs: np.ndarray) -> np.ndarray:
        self.request.infer({0: inputs}, share_inputs=True, share_outputs=True)
        return self.request.get_output_tensor(0).data.copy()

    def close(self) -> None:
        self.request = None
        self.compiled = None


class CudaGraphBackend(Backend):
    """PyTorch on a CUDA device, replaying CUDA graphs.

    Frames live on the device in a doubled uint8 ring (slots ``i`` and ``i + span``);
    one graph per ring position runs the full module on the contiguous view
    ``ring[head + 1 : head + 1 + span]``, so streaming copies only the new frame to
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
        n, s = self.span, self.image_size
        self._ring = torch.zeros((1, 2 * n, s, s, 3), dtype=torch.uint8, device=self.device)
        # the rest image (rest-referenced models): (1, 1, S, S, 3), and the array it holds
        self._rest = torch.zeros((1, self.rest, s, s, 3), dtype=torch.uint8, device=self.device)
        self._rest_src: np.ndarray | None = None
        self._head = n - 1
        self._streaming = False  # True while the ring holds the stream's last span frames
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

    def _forward(self, head: int) -> torch.Tensor:
        window = self._ring[:, head + 1 : head + 1 + self.span]
        images = torch.cat([self._rest, window], dim=1) if self.rest else window
        with self._context():
            return self.module(images).float()

    @torch.inference_mode()
    def _capture(self) -> None:
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(3):  # warm-up: cuDNN algorithm choice, allocator
                self._forward(self.span - 1)
        torch.cuda.current_stream(self.device).wait_stream(side)
        pool = None
        for head in range(self.span):
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
        n = self.span
        for frame in frames[-n:]:
            head = (self._head + 1) % n
            x = torch.from_numpy(frame).to(self.device, non_blocking=False)
            self._ring[0, head] = x
            self._ring[0, head + n] = x
            self._head = head

    def _load(self, window: np.ndarray) -> None:
        """Copy a whole (1, span, S, S, 3) window into both halves of the ring."""
        n = self.span
        x = torch.from_numpy(window[0]).to(self.device)
        self._ring[0, :n] = x
        self._ring[0, n:] = x
        self._head = n - 1

    def _set_rest(self, rest: np.ndarray | None) -> None:
        """Copy the (S, S, 3) rest image to the device when it changed."""
        if rest is not None and self._rest_src is not rest:
            if self._rest_src is None or not np.array_equal(self._rest_src, rest):
                self._rest[0, 0] = torch.from_numpy(np.array(rest, order="C")).to(self.device)
            self._rest_src = rest

    @torch.inference_mode()
    def _run(self, images: np.ndarray) -> np.ndarray:
        if self.rest:
            self._rest[0, 0] = torch.from_numpy(images[0, 0]).to(self.device)
            self._rest_src = None
        self._load(images[:, self.rest :])
        self._streaming = False  # the ring no longer holds the stream's frames
        return self._compute()

    @torch.inference_mode()
    def run_incremental(
        self, window: np.ndarray, new_frames: int, rest: np.ndarray | None = None
    ) -> np.ndarray:
        self._check(window, (1, self.span, *self._shape[2:]))
        self._check_rest(rest)
        self._set_rest(rest)
        if new_frames >= self.span or not self._streaming:
            self._load(np.ascontiguousarray(window))
        elif new_frames > 0:
            self._push(window[0, self.span - int(new_frames) :])
        self._streaming = True
        return self._compute()

    def close(self) -> None:
        self._graphs.clear()
        self._outputs.clear()
        self._ring = None
