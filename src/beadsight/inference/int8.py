"""INT8: OpenVINO running the model after NNCF post-training quantization.

The checkpoint's network is exported to ONNX on float32 input planes (the same cached
file the ``onnx`` and ``openvino`` runtimes use; streaming computes each frame's planes
once, :mod:`beadsight.inference.planes`), quantized by :func:`nncf.quantize` on
**simulated windows that include presses** (:func:`calibration_windows`: the simulator
at the model's size, a seed the metric gate never uses), and saved as OpenVINO IR under
``cache_dir/int8`` keyed by the checkpoint's fingerprint, the machine, the calibration,
the recipe and the graph; later runs load it.

The recipes (:class:`QuantizationRecipe`) were chosen by the metric gate. Every recipe
leaves the pressure map itself in fp32: NNCF otherwise puts a quantizer on the model's
output, which cut each map at the calibration presses' peak in 256 levels (on 16
held-out presses the shipped model's force error moved by +31 %). NNCF's defaults
(symmetric activations, ranges averaged over the calibration windows, every convolution
in int8: :data:`NNCF_DEFAULT`) clip the activations of hard presses: MAE +18 %, force
error +31 % on the shipped model. Asymmetric activations (the ``mixed`` preset) with
min/max ranges, and the full-resolution blocks (the first and last conv blocks and the
output conv, about 40 % of the convolution work at the reference size) kept in fp32
(:data:`ACCURATE`), sit about the gate's 2 % edge: the shipped model's CoP error moves
by +1.7 % (AVX-512 VNNI, 2 threads) to +4.9 % (1 thread), every other metric by under
1.6 %; the reference-size model's MAE by +2.0 % (docs/live.md); further training
(with ``beadsight train --qat``, :mod:`beadsight.train.qat`, or without) brought it
within the gate. Much of that error was the quantizers NNCF still put on ``C1``'s norms
(``whole_blocks``): quantizing the last conv block too, with the first block kept
whole (:data:`FAST`, about 1.1x :data:`ACCURATE` at the reference size), keeps the
reference-size model within the gate (every metric within 1 % on two sets of held-out
presses; before the further training too) but not the shipped model (CoP +6 %).
:data:`FASTEST` quantizes ``C1``'s first convolution too (its input planes, each frame's
change from the rest image, at about two pixel levels a step), 1.15x :data:`FAST` at the
reference size with the same metric changes there, a 30 s held press read as fp32
reads it; its graph takes the planes as uint8, quantized once per frame by the ring
(:func:`_take_uint8_planes`). So the gated runtime tries :data:`RECIPES` fastest first
and runs the first that passes.

Whether the result may be used is decided on the paper's metrics, not pixel by pixel:
:func:`beadsight.inference.metric_parity.metric_parity` (the ``int8`` runtime and auto
selection both apply it through :func:`gated_int8`, which keeps each recipe's verdict
beside the model and refuses a model whose fp32 metrics cannot vouch before quantizing
it).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import re
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.errors import ConfigError
from beadsight.files import atomic_write, atomic_write_json
from beadsight.inference.backend import BackendUnavailableError
from beadsight.inference.config import INT8
from beadsight.inference.export_format import model_fingerprint
from beadsight.inference.machine import import_openvino, machine_key, openvino_signal_stack_kept
from beadsight.inference.metric_parity import (
    GATE_KEY,
    HELDOUT_PRESSES,
    METRIC_TOLERANCE,
    WINDOWS_PER_PRESS,
    MetricParity,
    SimulatedPresses,
    fp32_maps,
    metric_parity,
    require_meaningful,
    require_metric_parity,
    simulated_presses,
)
from beadsight.inference.planes import GRAPH_VERSION, PlaneQuantizer, PlaneRing, ring_inputs
from beadsight.inference.runtimes import OpenVinoBackend

log = logging.getLogger(__name__)

CALIBRATION_SEED = 4242  # simulator seed of the calibration presses (not the gate's)
CALIBRATION_PRESSES = 3
CALIBRATION_WINDOWS_PER_PRESS = 10  # 30 windows: NNCF's statistics need a few dozen
CALIBRATION_CONTACT_SHARE = 0.75  # most calibration windows in contact: the peaks' range
CALIBRATION_VERSION = "sim-presses-v2"  # change when the calibration windows change


@dataclass(frozen=True)
class QuantizationRecipe:
    """How NNCF quantizes: preset, activation ranges and the blocks kept in fp32.

    ``fp32_blocks`` keeps those U-Net submodules' convolutions in fp32. OpenVINO names the
    instance norms of a conv block apart from it (``MVN_74``), so NNCF still quantizes
    their inputs (each conv's output) unless ``whole_blocks``, which keeps every node from
    a block's first convolution to its last ELU in fp32."""

    preset: str = "mixed"  # "mixed": asymmetric activations; "performance": symmetric
    ranges: str = "minmax"  # "minmax": widest seen; "mean_minmax": NNCF's default average
    fp32_blocks: tuple[str, ...] = ("C1", "C9", "pred")  # UNet submodules not quantized
    whole_blocks: bool = False  # the fp32 conv blocks' norms too
    first_conv_int8: bool = False  # with whole_blocks: each such block's first conv in int8

    def __post_init__(self) -> None:
        if self.preset not in ("mixed", "performance"):
            raise ConfigError(f"preset must be 'mixed' or 'performance', got {self.preset!r}")
        if self.ranges not in ("minmax", "mean_minmax"):
            raise ConfigError(f"ranges must be 'minmax' or 'mean_minmax', got {self.ranges!r}")
        if self.first_conv_int8 and not self.whole_blocks:
            raise ConfigError("first_conv_int8 applies to blocks kept whole (whole_blocks)")

    @property
    def key(self) -> str:
        blocks = "+".join(self.fp32_blocks) or "all"
        whole = "-whole" if self.whole_blocks else ""
        conv0 = "-conv0int8" if self.first_conv_int8 else ""
        return f"{self.preset}-{self.ranges}-{blocks}{whole}{conv0}-fp32out"

    def nncf_options(self, nncf, graph: str = "onnx") -> dict:
        """Keyword arguments of :func:`nncf.quantize` for this recipe, on the model as
        the runtimes export it (``graph="onnx"``) or on the torch U-Net itself ("torch":
        quantization-aware training, :mod:`beadsight.train.qat`)."""
        from nncf.quantization.advanced_parameters import AdvancedQuantizationParameters
        from nncf.quantization.range_estimator import RangeEstimatorParametersSet

        options: dict = {
            "preset": nncf.QuantizationPreset.MIXED
            if self.preset == "mixed"
            else nncf.QuantizationPreset.PERFORMANCE
        }
        if self.ranges == "minmax":
            options["advanced_parameters"] = AdvancedQuantizationParameters(
                activations_range_estimator_params=RangeEstimatorParametersSet.MINMAX
            )
        # The pressure map itself is never quantized: NNCF puts a quantizer on the output
        # ReLU for the Gather that picks its channel (`[:, 0]`), which cut every map at the
        # calibration presses' peak (140 kPa for the shipped model) in steps of 1/255 of it.
        blocks = "|".join(self.fp32_blocks)
        if graph == "torch":  # node names of NNCF's torch graph: C1/layer/0/conv2d/0
            # (the network's output is the U-Net's; its channel is picked outside it)
            patterns = [f"({blocks})/.*"] if blocks else []
            options["ignored_scope"] = nncf.IgnoredScope(patterns=patterns)
            return options
        whole = [b for b in self.fp32_blocks if self.whole_blocks and re.fullmatch(r"C\d+", b)]
        # by name: every node of the block (/net/C1/layer/layer.0/Conv), but a first conv
        # left to int8 (its input quantized) is kept out only by its block's subgraph
        named = "|".join(b for b in self.fp32_blocks if not (self.first_conv_int8 and b in whole))
        patterns = [f".*/net/({named})/.*"] if named else []
        start = "Conv" if self.first_conv_int8 else "Conv/WithoutBiases"  # its bias add, or it
        subgraphs = [
            nncf.Subgraph(
                inputs=[f"/net/{b}/layer/layer.0/{start}"],
                outputs=[f"/net/{b}/layer/layer.6/Elu"],  # ConvBlock: conv, norm, ELU, twice
            )
            for b in whole
        ]
        options["ignored_scope"] = nncf.IgnoredScope(
            patterns=patterns, types=["Gather"], subgraphs=subgraphs
        )
        return options


ACCURATE = QuantizationRecipe()  # the default: passes the metric gate on the shipped model
FAST = QuantizationRecipe(fp32_blocks=("C1", "pred"), whole_blocks=True)  # C9 in int8 too
FASTEST = QuantizationRecipe(  # and C1's first conv: its input planes quantized
    fp32_blocks=("C1", "pred"), whole_blocks=True, first_conv_int8=True
)
RECIPES = (FASTEST, FAST, ACCURATE)  # what the gated runtime tries, fastest first
NNCF_DEFAULT = QuantizationRecipe("performance", "mean_minmax", ())  # fails it (measured)


def calibration_windows(model: PressureModel) -> np.ndarray:
    """(K, inputs, S, S, 3) uint8 RGB windows of simulated presses (most in contact)."""
    presses = simulated_presses(
        model,
        CALIBRATION_PRESSES,
        CALIBRATION_SEED,
        CALIBRATION_WINDOWS_PER_PRESS,
        CALIBRATION_CONTACT_SHARE,
    )
    return presses.inputs()


def _model_key(model: PressureModel, windows: np.ndarray | None, recipe: QuantizationRecipe) -> str:
    """Names a quantized model: the checkpoint, the machine, the calibration and recipe."""
    return f"{model_fingerprint(model)[:24]}-{machine_key()}-{_calibration_key(windows, recipe)}"


def _calibration_key(windows: np.ndarray | None, recipe: QuantizationRecipe) -> str:
    if windows is None:
        recipe_text = f"{CALIBRATION_VERSION}|{CALIBRATION_SEED}|{CALIBRATION_PRESSES}"
        data = f"{recipe_text}|{CALIBRATION_WINDOWS_PER_PRESS}".encode()
    else:
        data = np.ascontiguousarray(windows).tobytes()
    return hashlib.sha256(data + f"{recipe.key}|{GRAPH_VERSION}".encode()).hexdigest()[:12]


def _openvino():
    try:
        ov = import_openvino()  # first: nncf must not load the telemetry either
        import nncf
    except ImportError:
        raise BackendUnavailableError(
            "int8: needs openvino and nncf; `pip install beadsight[openvino]`"
        ) from None
    return ov, nncf


def quantize(
    onnx_path: Path,
    shape: tuple[int, ...],
    windows: np.ndarray,
    out: Path,
    recipe: QuantizationRecipe = ACCURATE,
    prepare: Callable[[np.ndarray], np.ndarray] = lambda images: images,
) -> Path:
    """Quantize the ONNX model at ``onnx_path`` (input reshaped to ``shape``) with NNCF on
    ``windows`` ((K, inputs, S, S, 3) uint8; ``prepare`` maps a batch of them to the
    graph's input) as ``recipe`` says; write OpenVINO IR ``out`` (.xml + .bin)."""
    ov, nncf = _openvino()
    ov_model = ov.Core().read_model(str(onnx_path))
    ov_model.reshape({ov_model.inputs[0]: list(shape)})
    data = nncf.Dataset(list(windows), lambda w: prepare(w[None]))
    nncf_log = logging.getLogger("nncf")  # its handler writes INFO lines to stdout
    level = nncf_log.level
    nncf_log.setLevel(logging.WARNING)
    try:
        # its progress bar: keep stdout clean; its statistics run on the CPU plugin
        with contextlib.redirect_stdout(sys.stderr), openvino_signal_stack_kept():
            quantized = nncf.quantize(
                ov_model, data, subset_size=len(windows), **recipe.nncf_options(nncf)
            )
    finally:
        nncf_log.setLevel(level)
    quantized = _take_uint8_planes(ov, quantized)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=".beadsight-") as tmp:
        staged = Path(tmp) / "model.xml"
        ov.save_model(quantized, str(staged), compress_to_fp16=False)
        for src, dst in ((staged.with_suffix(".bin"), out.with_suffix(".bin")), (staged, out)):
            atomic_write(dst, lambda f, src=src: f.write(src.read_bytes()))
    return out


def _constant(node) -> float | None:
    """A scalar Constant node's value, else None."""
    if node.get_type_name() != "Constant":
        return None
    data = np.asarray(node.get_data())
    return float(data.ravel()[0]) if data.size == 1 else None


def _take_uint8_planes(ov, model):
    """When the graph's first step quantizes its input planes (one per-tensor
    FakeQuantize of 256 levels, the same range in and out, an integral zero point), the
    graph that takes them quantized: a uint8 input read as ``(q - zero_point) * scale``,
    which OpenVINO's CPU plugin runs as the same int8 convolution (bit-identical maps on
    the reference-size model), while the ring quantizes each frame once
    (:class:`~beadsight.inference.planes.PlaneQuantizer`). Else the graph unchanged."""
    (param,) = model.get_parameters()
    users = [t.get_node() for t in param.output(0).get_target_inputs()]
    if len(users) != 1 or users[0].get_type_name() != "FakeQuantize":
        return model
    fq = users[0]
    lo, hi, out_lo, out_hi = (
        _constant(fq.input(i).get_source_output().get_node()) for i in (1, 2, 3, 4)
    )
    if None in (lo, hi) or (lo, hi) != (out_lo, out_hi) or fq.get_levels() != 256 or hi <= lo:
        return model
    scale = (hi - lo) / 255
    zero_point = -lo / scale
    if abs(zero_point - round(zero_point)) > 1e-3 or not 0 <= round(zero_point) <= 255:
        return model
    ops = ov.opset13
    planes = ops.parameter(param.get_output_partial_shape(0), ov.Type.u8, name="planes")
    shifted = ops.subtract(ops.convert(planes, ov.Type.f32), np.float32(round(zero_point)))
    dequantized = ops.multiply(shifted, np.float32(scale))
    for target in list(fq.output(0).get_target_inputs()):
        target.replace_source_output(dequantized.output(0))
    return ov.Model(model.get_results(), [planes], model.get_friendly_name())


def _input_quantizer(model) -> PlaneQuantizer | None:
    """The quantizer of a graph made by :func:`_take_uint8_planes` (None for one that
    takes float32 planes)."""
    (param,) = model.get_parameters()
    if param.get_element_type().get_type_name() != "u8":
        return None
    (convert,) = [t.get_node() for t in param.output(0).get_target_inputs()]
    (subtract,) = [t.get_node() for t in convert.output(0).get_target_inputs()]
    (multiply,) = [t.get_node() for t in subtract.output(0).get_target_inputs()]
    zero_point = _constant(subtract.input(1).get_source_output().get_node())
    scale = _constant(multiply.input(1).get_source_output().get_node())
    return PlaneQuantizer(int(zero_point), scale)


class Int8Backend(OpenVinoBackend):
    """OpenVINO on an NNCF-quantized copy of the model (module docstring).

    calibration: (K, inputs, S, S, 3) uint8 windows to calibrate on instead of
    :func:`calibration_windows`; recipe: how to quantize (default :data:`ACCURATE`). A
    model calibrated on other data or by another recipe is cached apart.
    """

    name = "int8"
    precisions = (INT8,)

    def __init__(
        self,
        model: PressureModel,
        precision: str = INT8,
        cache_dir: Path | None = None,
        threads: int | None = None,
        calibration: np.ndarray | None = None,
        recipe: QuantizationRecipe = ACCURATE,
    ):
        self._calibration = calibration
        self.recipe = recipe
        self.model_key = _model_key(model, calibration, recipe)
        super().__init__(model, precision, None, cache_dir, threads)

    def _check_available(self) -> None:
        _openvino()

    def _load(self, path: Path, threads: int, cache_dir: Path | None) -> None:
        ov, _ = _openvino()
        folder = Path(cache_dir) / "int8" if cache_dir else Path(tempfile.mkdtemp(prefix="bs-"))
        xml = folder / f"{self.model_key}.xml"
        if not (xml.is_file() and xml.with_suffix(".bin").is_file()):
            windows = self._calibration
            if windows is None:
                windows = calibration_windows(self.model)
            log.info("int8: quantizing with NNCF on %d simulated windows -> %s", len(windows), xml)
            prepare = lambda images: ring_inputs(self.model.module, images)  # noqa: E731
            quantize(path, self.input_shape, windows, xml, self.recipe, prepare)
        else:
            log.info("int8: loading cached %s", xml)
        config = {
            "INFERENCE_PRECISION_HINT": "f32",  # what is not quantized stays fp32
            "INFERENCE_NUM_THREADS": threads,
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,
        }
        with openvino_signal_stack_kept():
            core = ov.Core()
            graph = core.read_model(str(xml))
            quantizer = _input_quantizer(graph)
            if quantizer is not None:  # the ring keeps each frame's planes quantized
                self.planes = PlaneRing(self.model.module, self.image_size, quantizer)
            self.compiled = core.compile_model(graph, "CPU", config)
        self.request = self.compiled.create_infer_request()
        self.config = config
        self.quantized_path = xml
        self.cache_dir = Path(cache_dir) if cache_dir else None


def _read_parity(path: Path | None, tolerance: float) -> MetricParity | None:
    try:
        data = json.loads(path.read_text())
        return MetricParity(
            data["backend"],
            data["reference"],
            data["candidate"],
            int(data["windows"]),
            data["zero"],
            tolerance,  # judged by today's bound, whatever it was when kept
        )
    except (AttributeError, OSError, ValueError, KeyError, TypeError):
        return None


def judged_int8(
    model: PressureModel,
    cache_dir: Path | None = None,
    threads: int | None = None,
    tolerance: float = METRIC_TOLERANCE,
    recipes: tuple[QuantizationRecipe, ...] = RECIPES,
    presses: SimulatedPresses | None = None,
    reference: np.ndarray | None = None,
) -> Int8Backend:
    """The int8 runtime of ``model`` by the first of ``recipes`` (fastest first) that
    passes the metric gate (every paper metric within ``tolerance`` relative to fp32
    torch), else by the last one, refused; its verdict is its ``parity``.

    Each recipe's verdict is kept in ``cache_dir/int8/<key>-parity-<gate>.json`` (the
    held-out ``presses``, by default :func:`simulated_presses`, run through fp32 torch
    once for all of them). A model whose fp32 metrics do no better than an all-zero map
    is refused (:class:`MetricParityError`) before anything is quantized."""
    for n, recipe in enumerate(recipes, 1):
        key = f"{_model_key(model, None, recipe)}-parity-{GATE_KEY}.json"
        path = Path(cache_dir) / "int8" / key if cache_dir else None
        parity = _read_parity(path, tolerance)
        backend = None
        if parity is None:
            if reference is None:
                log.info(
                    "int8: judging it on the paper's metrics against fp32 torch on %d "
                    "windows of %d held-out simulated presses, once for this checkpoint "
                    "and machine%s",
                    HELDOUT_PRESSES * WINDOWS_PER_PRESS,
                    HELDOUT_PRESSES,
                    f" (the verdicts are kept in {path.parent})" if path else "",
                )
                presses = simulated_presses(model) if presses is None else presses
                reference = fp32_maps(model, presses)
                require_meaningful(model, presses, reference)
            backend = Int8Backend(model, cache_dir=cache_dir, threads=threads, recipe=recipe)
            parity = metric_parity(
                backend, model, presses, reference=reference, tolerance=tolerance
            )
            if path is not None:
                atomic_write_json(path, parity.to_dict())
        log.info(
            "int8: recipe %s %s the metric gate: %s",
            recipe.key,
            "passes" if parity.ok else "fails",
            parity,
        )
        if parity.ok or n == len(recipes):
            backend = backend or Int8Backend(
                model, cache_dir=cache_dir, threads=threads, recipe=recipe
            )
            backend.parity = parity
            return backend
        if backend is not None:
            backend.close()
    raise ConfigError("judged_int8: no recipes given")


def gated_int8(
    model: PressureModel,
    cache_dir: Path | None = None,
    threads: int | None = None,
    tolerance: float = METRIC_TOLERANCE,
    recipes: tuple[QuantizationRecipe, ...] = RECIPES,
) -> Int8Backend:
    """:func:`judged_int8`'s runtime if it passes the metric gate, else
    :class:`~beadsight.inference.metric_parity.MetricParityError` (the backend closed)."""
    backend = judged_int8(model, cache_dir, threads, tolerance, recipes)
    require_metric_parity(backend, model, backend.parity)
    return backend
