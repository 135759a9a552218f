"""INT8: OpenVINO running the model after NNCF post-training quantization.

The checkpoint is exported to ONNX (the same cached file the ``onnx`` and ``openvino``
runtimes use), quantized by :func:`nncf.quantize` on **simulated windows that include
presses** (:func:`calibration_windows`: the simulator at the model's size, a seed the
metric gate never uses), and saved as OpenVINO IR under ``cache_dir/int8`` keyed by the
checkpoint's fingerprint, the machine and the calibration; later runs load it. The
instance norms and the output stay in floating point (NNCF's default for them).

Whether the result may be used is decided on the paper's metrics, not pixel by pixel:
:func:`beadsight.inference.metric_parity.metric_parity` (the ``int8`` runtime and auto
selection both apply it; :func:`cached_metric_parity` keeps its result beside the model).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.files import atomic_write, atomic_write_json
from beadsight.inference.backend import BackendUnavailableError
from beadsight.inference.config import INT8
from beadsight.inference.exported import model_fingerprint
from beadsight.inference.machine import machine_key
from beadsight.inference.metric_parity import (
    MetricParity,
    metric_parity,
    simulated_presses,
)
from beadsight.inference.runtimes import OpenVinoBackend

log = logging.getLogger(__name__)

CALIBRATION_SEED = 4242  # simulator seed of the calibration presses (not the gate's)
CALIBRATION_PRESSES = 3
CALIBRATION_WINDOWS_PER_PRESS = 10  # 30 windows: NNCF's statistics need a few dozen
CALIBRATION_VERSION = "sim-presses-v1"  # change when the calibration recipe changes


def calibration_windows(model: PressureModel) -> np.ndarray:
    """(K, inputs, S, S, 3) uint8 RGB windows of simulated presses (most in contact)."""
    presses = simulated_presses(
        model, CALIBRATION_PRESSES, CALIBRATION_SEED, CALIBRATION_WINDOWS_PER_PRESS
    )
    return presses.inputs


def _calibration_key(windows: np.ndarray | None) -> str:
    if windows is None:
        recipe = f"{CALIBRATION_VERSION}|{CALIBRATION_SEED}|{CALIBRATION_PRESSES}"
        text = f"{recipe}|{CALIBRATION_WINDOWS_PER_PRESS}"
        return hashlib.sha256(text.encode()).hexdigest()[:12]
    return hashlib.sha256(np.ascontiguousarray(windows).tobytes()).hexdigest()[:12]


def _openvino():
    try:
        import nncf
        import openvino as ov
    except ImportError:
        raise BackendUnavailableError(
            "int8: needs openvino and nncf; `pip install beadsight[openvino]`"
        ) from None
    return ov, nncf


def quantize(onnx_path: Path, shape: tuple[int, ...], windows: np.ndarray, out: Path) -> Path:
    """Quantize the ONNX model at ``onnx_path`` (input reshaped to ``shape``) with NNCF on
    ``windows`` ((K, inputs, S, S, 3) uint8); write OpenVINO IR ``out`` (.xml + .bin)."""
    ov, nncf = _openvino()
    ov_model = ov.Core().read_model(str(onnx_path))
    ov_model.reshape({ov_model.inputs[0]: list(shape)})
    data = nncf.Dataset(list(windows), lambda w: w[None])
    with contextlib.redirect_stdout(sys.stderr):  # NNCF's progress bar: keep stdout clean
        quantized = nncf.quantize(ov_model, data, subset_size=len(windows))
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=".beadsight-") as tmp:
        staged = Path(tmp) / "model.xml"
        ov.save_model(quantized, str(staged), compress_to_fp16=False)
        for src, dst in ((staged.with_suffix(".bin"), out.with_suffix(".bin")), (staged, out)):
            atomic_write(dst, lambda f, src=src: f.write(src.read_bytes()))
    return out


class Int8Backend(OpenVinoBackend):
    """OpenVINO on an NNCF-quantized copy of the model (module docstring).

    calibration: (K, inputs, S, S, 3) uint8 windows to calibrate on instead of
    :func:`calibration_windows` (a model calibrated on other data is cached apart).
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
    ):
        self._calibration = calibration
        self.model_key = f"{model_fingerprint(model)[:24]}-{machine_key()}-"
        self.model_key += _calibration_key(calibration)
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
            quantize(path, self._shape, windows, xml)
        else:
            log.info("int8: loading cached %s", xml)
        config = {
            "INFERENCE_PRECISION_HINT": "f32",  # what is not quantized stays fp32
            "INFERENCE_NUM_THREADS": threads,
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,
        }
        self.compiled = ov.Core().compile_model(str(xml), "CPU", config)
        self.request = self.compiled.create_infer_request()
        self.config = config
        self.quantized_path = xml
        self.cache_dir = Path(cache_dir) if cache_dir else None


def cached_metric_parity(backend: Int8Backend, model: PressureModel) -> MetricParity:
    """:func:`metric_parity` of ``backend``, kept in ``cache_dir/int8/<key>-parity.json``
    (the held-out presses are simulated and run through fp32 torch only once)."""
    path = None
    if backend.cache_dir is not None:
        path = backend.cache_dir / "int8" / f"{backend.model_key}-parity.json"
        try:
            data = json.loads(path.read_text())
            return MetricParity(
                data["backend"],
                data["reference"],
                data["candidate"],
                int(data["windows"]),
                data["zero"],
            )
        except (OSError, ValueError, KeyError, TypeError):
            pass
    parity = metric_parity(backend, model)
    if path is not None:
        atomic_write_json(path, parity.to_dict())
    return parity
