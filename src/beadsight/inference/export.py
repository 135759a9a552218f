"""Export a checkpoint to ONNX or OpenVINO IR, with its normalisation and metadata.

The exported graph is the whole :class:`~beadsight.model.FramesToPressure`
module: it takes ``frames`` (B, T, S, S, 3) uint8 RGB, oldest frame first, and
returns ``pressure_kpa`` (B, S, S) float32 kPa (the batch axis is dynamic). The
checkpoint's metadata travels inside the file (ONNX ``metadata_props``,
OpenVINO ``rt_info`` under ``beadsight``):

* ``beadsight``: the checkpoint metadata JSON (model config, window, geometry,
  normalisation, channel order, output scale, provenance);
* ``beadsight_weights_sha256``: fingerprint of the weights and metadata
  (:func:`model_fingerprint`), used to refuse an exported file next to the wrong
  checkpoint;
* ``beadsight_version``, ``beadsight_input``, ``beadsight_output``, and
  ``beadsight_precision`` (the precision the file was exported for).

Using an exported ONNX file without beadsight (only numpy and onnxruntime)::

    import json, numpy as np, onnxruntime as ort
    session = ort.InferenceSession("beadsight.onnx")
    meta = json.loads(session.get_modelmeta().custom_metadata_map["beadsight"])
    m, s = meta["model"], meta["geometry"]["image_size_px"]
    t = (m["window"] - 1) * m.get("frame_stride", 1) + 1  # frames per input window
    frames = np.zeros((1, t, s, s, 3), np.uint8)  # the last t RGB frames, oldest first
    pressure_kpa = session.run(None, {"frames": frames})[0][0]  # (S, S) float32 kPa

Every export runs a parity check against the torch model on the probe windows
(:func:`beadsight.inference.runtimes.probe_windows`) and refuses to keep a file that
disagrees: fp32 within ``max(1e-4 kPa, 1e-5 x peak)`` (float32 rounding grows
with the map's magnitude), bf16 within 1 % of ``max(peak, floor)``
(:data:`beadsight.inference.runtimes.PARITY_TOLERANCE`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from beadsight import __version__
from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.errors import BeadSightError, ConfigError
from beadsight.inference.config import EXPORT_FORMATS as FORMATS
from beadsight.inference.config import EXPORT_PRECISIONS

log = logging.getLogger(__name__)

ONNX_OPSET = 17
INPUT_NAME = "frames"
OUTPUT_NAME = "pressure_kpa"
META_KEY = "beadsight"
FINGERPRINT_KEY = "beadsight_weights_sha256"
PRECISION_KEY = "beadsight_precision"
FP32_ABS_TOLERANCE_KPA = 1e-4  # export parity bound for fp32 files
FP32_REL_TOLERANCE = 1e-5  # ... or this fraction of the probe's peak, if larger (float32 rounding)


class ExportError(BeadSightError):
    """An export failed its parity check, or an exported file does not fit its use."""


@dataclass(frozen=True)
class ExportReport:
    """What :func:`export_model` wrote and how well it agrees with torch."""

    path: str
    format: str
    precision: str
    max_abs_err_kpa: float
    tolerance_kpa: float
    peak_kpa: float
    fingerprint: str

    def to_dict(self) -> dict:
        return asdict(self)


# --- metadata -----------------------------------------------------------------------
def model_fingerprint(model: PressureModel) -> str:
    """sha256 over the metadata JSON and every weight tensor (sorted by name)."""
    h = hashlib.sha256(model.meta.to_json().encode())
    for name, tensor in sorted(model.module.net.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()


def exported_metadata(model: PressureModel, precision: str = "fp32") -> dict[str, str]:
    """The key -> string metadata stored in exported files."""
    t, s = model.window, model.image_size
    return {
        META_KEY: model.meta.to_json(),
        FINGERPRINT_KEY: model_fingerprint(model),
        "beadsight_version": __version__,
        "beadsight_input": f"{INPUT_NAME}: (B, {t}, {s}, {s}, 3) uint8 RGB 0..255, oldest first",
        "beadsight_output": f"{OUTPUT_NAME}: (B, {s}, {s}) float32 kPa",
        PRECISION_KEY: precision,
    }


def read_exported_metadata(path: str | Path) -> dict[str, str]:
    """The beadsight metadata of an exported ``.onnx`` or OpenVINO ``.xml`` file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: exported model not found")
    if path.suffix == ".onnx":
        onnx = _require("onnx", "export")
        proto = onnx.load(str(path), load_external_data=False)
        meta = {p.key: p.value for p in proto.metadata_props}
    elif path.suffix == ".xml":
        ov = _require("openvino", "openvino")
        model = ov.Core().read_model(str(path))
        meta = {}
        if model.has_rt_info([META_KEY]):
            for key, value in model.get_rt_info()[META_KEY].items():
                meta[key] = value.astype(str) if hasattr(value, "astype") else str(value)
    else:
        raise ExportError(f"{path}: unknown exported model type; expected .onnx or .xml")
    if META_KEY not in meta or FINGERPRINT_KEY not in meta:
        raise ExportError(
            f"{path}: no beadsight metadata ({META_KEY!r}, {FINGERPRINT_KEY!r}); "
            "export it with `beadsight export`"
        )
    return meta


def check_exported_matches(path: str | Path, model: PressureModel) -> dict[str, str]:
    """Raise :class:`ExportError` unless ``path`` was exported from ``model``'s weights."""
    meta = read_exported_metadata(path)
    if meta[FINGERPRINT_KEY] != model_fingerprint(model):
        theirs = json.loads(meta[META_KEY])
        mine = json.loads(model.meta.to_json())
        differing = sorted(k for k in set(theirs) | set(mine) if theirs.get(k) != mine.get(k))
        detail = (
            f"metadata differs in {', '.join(differing)}" if differing else "the weights differ"
        )
        raise ExportError(
            f"{path} was exported from a different checkpoint than {model.source} ({detail}); "
            "re-export it with `beadsight export --checkpoint ...`"
        )
    return meta


def _export_tolerance(precision: str):
    """fp32: max(1e-4 kPa, 1e-5 x peak); bf16: the backends' 1 % of max(peak, floor)."""
    from beadsight.inference.runtimes import PARITY_TOLERANCE, ParityTolerance

    if precision != "fp32":
        return PARITY_TOLERANCE
    return ParityTolerance(
        fraction=FP32_REL_TOLERANCE, floor_kpa=0.0, abs_kpa=FP32_ABS_TOLERANCE_KPA
    )


# --- writing ------------------------------------------------------------------------
def _require(module: str, extra: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise BeadSightError(
            f"{module} is not installed; install it with `pip install beadsight[{extra}]`"
        ) from None


def write_onnx(model: PressureModel, path: str | Path, precision: str = "fp32") -> Path:
    """Export ``model.module`` to ONNX at ``path`` with metadata (no parity check)."""
    onnx = _require("onnx", "export")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    module = model.module
    device = model.device
    shape = (1, model.window, model.image_size, model.image_size, 3)
    fd, tmp = tempfile.mkstemp(suffix=".onnx", dir=path.parent)
    os.close(fd)
    module.to("cpu")
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # legacy-exporter deprecation, instance_norm notes
            torch.onnx.export(
                module,
                (torch.zeros(shape, dtype=torch.uint8),),
                tmp,
                dynamo=False,
                input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME],
                dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                opset_version=ONNX_OPSET,
            )
        proto = onnx.load(tmp)
        del proto.metadata_props[:]
        for key, value in exported_metadata(model, precision).items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        proto.doc_string = (
            "BeadSight pressure model: uint8 RGB frame window -> kPa map. See metadata "
            f"'{META_KEY}' for the window, geometry and units."
        )
        onnx.save(proto, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    finally:
        module.to(device)
    return path


def write_openvino(model: PressureModel, path: str | Path, precision: str = "fp32") -> Path:
    """Export to OpenVINO IR (``path`` = the ``.xml``; a ``.bin`` is written beside it)."""
    ov = _require("openvino", "openvino")
    path = Path(path)
    if path.suffix != ".xml":
        raise ExportError(f"{path}: an OpenVINO model path must end in .xml")
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        onnx_path = write_onnx(model, Path(tmp) / "model.onnx", precision)
        ov_model = ov.convert_model(str(onnx_path))
    for key, value in exported_metadata(model, precision).items():
        ov_model.set_rt_info(value, [META_KEY, key])
    # weights stay fp32 in the file; bf16 is an inference precision chosen at load time
    ov.save_model(ov_model, str(path), compress_to_fp16=False)
    return path


def export_model(
    checkpoint: PressureModel | str | Path,
    format: str,
    out: str | Path,
    precision: str = "fp32",
    threads: int | None = None,
) -> ExportReport:
    """Export, then check the file against torch; a file that disagrees is deleted.

    returns: an :class:`ExportReport` with the measured max abs error in kPa.
    """
    from beadsight.inference.runtimes import check_parity, open_exported

    if format not in FORMATS:
        raise ConfigError(f"format must be one of {FORMATS}, got {format!r}")
    if precision not in EXPORT_PRECISIONS:
        raise ConfigError(f"precision must be one of {EXPORT_PRECISIONS}, got {precision!r}")
    if format == "onnx" and precision != "fp32":
        raise ExportError(
            "ONNX export is fp32 only (onnxruntime's CPU provider has no bf16 convolutions); "
            "use --format openvino --precision bf16"
        )
    model = checkpoint if isinstance(checkpoint, PressureModel) else load_checkpoint(checkpoint)
    out = Path(out)
    if format == "openvino" and out.suffix != ".xml":
        out = out.with_suffix(".xml") if out.suffix else out / "model.xml"
    writer = write_onnx if format == "onnx" else write_openvino
    path = writer(model, out, precision)
    backend = open_exported(path, model, precision=precision, threads=threads, check=False)
    try:
        tolerance = _export_tolerance(precision)
        parity = check_parity(backend, model, tolerance=tolerance)
    finally:
        backend.close()
    err, tol, peak = parity.max_abs_err_kpa, parity.tolerance_kpa, parity.peak_kpa
    report = ExportReport(str(path), format, precision, err, tol, peak, model_fingerprint(model))
    if not err <= tol:
        for written in {path, path.with_suffix(".bin") if format == "openvino" else path}:
            written.unlink(missing_ok=True)
        raise ExportError(
            f"{path}: exported {format} ({precision}) disagrees with torch: max abs error "
            f"{err:.3g} kPa > {tol:.3g} kPa (peak {peak:.3g} kPa); file removed"
        )
    log.info("exported %s: max abs error %.3g kPa (tolerance %.3g)", path, err, tol)
    return report
