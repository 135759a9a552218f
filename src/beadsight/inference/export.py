"""Export a checkpoint to ONNX or OpenVINO IR, checked against torch before it is kept.

The file format (the graph's input and output, the metadata it carries) is described
in :mod:`beadsight.inference.export_format`, which writes and reads it.

Using an exported ONNX file without beadsight (only numpy and onnxruntime)::

    import json, numpy as np, onnxruntime as ort
    session = ort.InferenceSession("beadsight.onnx")
    meta = json.loads(session.get_modelmeta().custom_metadata_map["beadsight"])
    m, s = meta["model"], meta["geometry"]["image_size_px"]
    t = (m["frames"] - 1) * m["frame_stride"] + 1  # the span: frames per input window
    frames = np.zeros((1, t, s, s, 3), np.uint8)  # the last t RGB frames, oldest first
    pressure_kpa = session.run(None, {"frames": frames})[0][0]  # (S, S) float32 kPa

Every export runs a parity check against the torch model on the probe windows
(:func:`beadsight.inference.parity.probe_windows`) and refuses to keep a file that
disagrees: fp32 within ``max(1e-4 kPa, 1e-5 x peak)`` (float32 rounding grows
with the map's magnitude), bf16 within 1 % of ``max(peak, floor)``
(:data:`beadsight.inference.parity.PARITY_TOLERANCE`).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.errors import ConfigError
from beadsight.files import refuse_existing
from beadsight.inference.config import EXPORT_FORMATS as FORMATS
from beadsight.inference.config import EXPORT_PRECISIONS
from beadsight.inference.export_format import (
    ExportError,
    model_fingerprint,
    write_onnx,
    write_openvino,
)
from beadsight.inference.parity import PARITY_TOLERANCE, ParityTolerance, check_parity
from beadsight.inference.select import open_exported

log = logging.getLogger(__name__)

FP32_ABS_TOLERANCE_KPA = 1e-4  # export parity bound for fp32 files
FP32_REL_TOLERANCE = 1e-5  # ... or this fraction of the probe's peak, if larger (float32 rounding)


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


def export_tolerance(precision: str) -> ParityTolerance:
    """fp32: max(1e-4 kPa, 1e-5 x peak); bf16: the runtimes' 1 % of max(peak, floor)."""
    if precision != "fp32":
        return PARITY_TOLERANCE
    return ParityTolerance(
        fraction=FP32_REL_TOLERANCE, floor_kpa=0.0, abs_kpa=FP32_ABS_TOLERANCE_KPA
    )


def _check_request(format: str, precision: str) -> None:
    if format not in FORMATS:
        raise ConfigError(f"format must be one of {FORMATS}, got {format!r}")
    if precision not in EXPORT_PRECISIONS:
        raise ConfigError(f"precision must be one of {EXPORT_PRECISIONS}, got {precision!r}")
    if format == "onnx" and precision != "fp32":
        raise ExportError(
            "ONNX export is fp32 only (onnxruntime's CPU provider has no bf16 convolutions); "
            "use --format openvino --precision bf16"
        )


def export_model(
    checkpoint: PressureModel | str | Path,
    format: str,
    out: str | Path,
    precision: str = "fp32",
    threads: int | None = None,
    overwrite: bool = False,
) -> ExportReport:
    """Export, then check the file against torch; a file that disagrees is deleted.

    An existing ``out`` (for OpenVINO: its ``.xml`` or ``.bin``) is refused unless ``overwrite``.

    returns: an :class:`ExportReport` with the measured max abs error in kPa.
    """
    _check_request(format, precision)
    model = checkpoint if isinstance(checkpoint, PressureModel) else load_checkpoint(checkpoint)
    out = Path(out)
    if format == "openvino" and out.suffix != ".xml":
        out = out.with_suffix(".xml") if out.suffix else out / "model.xml"
    for path in (out, out.with_suffix(".bin")) if format == "openvino" else (out,):
        refuse_existing(path, overwrite)
    writer = write_onnx if format == "onnx" else write_openvino
    path = writer(model, out, precision)
    backend = open_exported(path, model, precision=precision, threads=threads, check=False)
    try:
        parity = check_parity(backend, model, tolerance=export_tolerance(precision))
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
