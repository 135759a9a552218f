"""The exported-model file format: ONNX and OpenVINO IR files with beadsight metadata.

An exported graph is the whole :class:`~beadsight.model.FramesToPressure` module: input
``frames`` (B, inputs, S, S, 3) uint8 RGB: for a rest-referenced model (``rest_input``
in the model config) the rest image first, then the window's span frames, oldest first;
output ``pressure_kpa``
(B, S, S) float32 kPa (the batch axis is dynamic). The checkpoint's metadata travels
inside the file (ONNX ``metadata_props``, OpenVINO ``rt_info`` under ``beadsight``):

* ``beadsight``: the checkpoint metadata JSON (model config with ``frames`` and
  ``frame_stride``, geometry, normalisation, channel order, output scale, provenance);
* ``beadsight_weights_sha256``: fingerprint of the weights and metadata
  (:func:`model_fingerprint`), used to refuse an exported file next to the wrong
  checkpoint;
* ``beadsight_version``, ``beadsight_input``, ``beadsight_output``, and
  ``beadsight_precision`` (the precision the file was exported for).

This module writes (:func:`write_onnx`, :func:`write_openvino`; no parity check) and
reads and verifies (:func:`read_exported_metadata`, :func:`check_exported_matches`)
such files. :func:`beadsight.inference.export.export_model` writes one and checks it
against torch.
"""

from __future__ import annotations

import hashlib
import importlib
import io
import json
import tempfile
import warnings
from pathlib import Path

import torch

from beadsight import __version__
from beadsight.checkpoint import PressureModel
from beadsight.errors import BeadSightError
from beadsight.files import atomic_write, atomic_write_bytes
from beadsight.inference.machine import import_openvino

ONNX_OPSET = 17
INPUT_NAME = "frames"
OUTPUT_NAME = "pressure_kpa"
META_KEY = "beadsight"
FINGERPRINT_KEY = "beadsight_weights_sha256"
PRECISION_KEY = "beadsight_precision"


class ExportError(BeadSightError):
    """An export failed its parity check, or an exported file does not fit its use."""


def require(module: str, extra: str):
    """Import an optional dependency, or say which extra installs it (openvino through
    :func:`~beadsight.inference.machine.import_openvino`)."""
    try:
        return import_openvino() if module == "openvino" else importlib.import_module(module)
    except ImportError:
        raise BeadSightError(
            f"{module} is not installed; install it with `pip install beadsight[{extra}]`"
        ) from None


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
    n, s = model.inputs, model.image_size
    layout = "the rest image, then the window oldest first" if model.rest else "oldest first"
    return {
        META_KEY: model.meta.to_json(),
        FINGERPRINT_KEY: model_fingerprint(model),
        "beadsight_version": __version__,
        "beadsight_input": f"{INPUT_NAME}: (B, {n}, {s}, {s}, 3) uint8 RGB 0..255, {layout}",
        "beadsight_output": f"{OUTPUT_NAME}: (B, {s}, {s}) float32 kPa",
        PRECISION_KEY: precision,
    }


def read_exported_metadata(path: str | Path) -> dict[str, str]:
    """The beadsight metadata of an exported ``.onnx`` or OpenVINO ``.xml`` file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: exported model not found")
    if path.suffix == ".onnx":
        onnx = require("onnx", "export")
        proto = onnx.load(str(path), load_external_data=False)
        meta = {p.key: p.value for p in proto.metadata_props}
    elif path.suffix == ".xml":
        ov = require("openvino", "openvino")
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
    if meta[FINGERPRINT_KEY] == model_fingerprint(model):
        return meta
    theirs = json.loads(meta[META_KEY])
    mine = json.loads(model.meta.to_json())
    differing = sorted(k for k in set(theirs) | set(mine) if theirs.get(k) != mine.get(k))
    detail = f"metadata differs in {', '.join(differing)}" if differing else "the weights differ"
    raise ExportError(
        f"{path} was exported from a different checkpoint than {model.source} ({detail}); "
        "re-export it with `beadsight export --checkpoint ...`"
    )


# --- writing ------------------------------------------------------------------------
def onnx_bytes(module: torch.nn.Module, example: torch.Tensor, input_name: str) -> bytes:
    """``module`` (on the CPU) exported to ONNX on ``example``, batch axis dynamic."""
    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # legacy-exporter deprecation, instance_norm notes
        torch.onnx.export(
            module,
            (example,),
            buffer,
            dynamo=False,
            input_names=[input_name],
            output_names=[OUTPUT_NAME],
            dynamic_axes={input_name: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
            opset_version=ONNX_OPSET,
        )
    return buffer.getvalue()


def _onnx_proto(model: PressureModel, precision: str):
    """The model's module as an ONNX ModelProto carrying the metadata."""
    onnx = require("onnx", "export")
    module, device = model.module, model.device
    shape = (1, model.inputs, model.image_size, model.image_size, 3)
    module.to("cpu")
    try:
        data = onnx_bytes(module, torch.zeros(shape, dtype=torch.uint8), INPUT_NAME)
    finally:
        module.to(device)
    proto = onnx.load_model_from_string(data)
    del proto.metadata_props[:]
    for key, value in exported_metadata(model, precision).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.doc_string = (
        "BeadSight pressure model: uint8 RGB frame window -> kPa map. See metadata "
        f"'{META_KEY}' for the frames, geometry and units."
    )
    return proto


def write_onnx(model: PressureModel, path: str | Path, precision: str = "fp32") -> Path:
    """Export ``model.module`` to ONNX at ``path`` with metadata (no parity check).

    Written atomically: a failed export leaves no file and any older ``path`` as it was.
    """
    proto = _onnx_proto(model, precision)
    return atomic_write_bytes(path, proto.SerializeToString())


def write_openvino(model: PressureModel, path: str | Path, precision: str = "fp32") -> Path:
    """Export to OpenVINO IR (``path`` = the ``.xml``; a ``.bin`` is written beside it).

    Both files are written atomically, the ``.bin`` first. The ONNX file is read by
    OpenVINO's ONNX frontend (``Core.read_model``), not its converter (``convert_model``):
    the converter sends usage telemetry to Google Analytics unless a consent file says
    otherwise, and writes ``~/intel``. The IR holds the graph as ONNX gives it;
    ``compile_model`` runs the same graph optimisations at load.
    """
    ov = require("openvino", "openvino")
    path = Path(path)
    if path.suffix != ".xml":
        raise ExportError(f"{path}: an OpenVINO model path must end in .xml")
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".beadsight-") as tmp:
        onnx_path = write_onnx(model, Path(tmp) / "model.onnx", precision)
        ov_model = ov.Core().read_model(str(onnx_path))
        for key, value in exported_metadata(model, precision).items():
            ov_model.set_rt_info(value, [META_KEY, key])
        # weights stay fp32 in the file; bf16 is an inference precision chosen at load time
        staged = Path(tmp) / "model.xml"
        ov.save_model(ov_model, str(staged), compress_to_fp16=False)
        for src, dst in ((staged.with_suffix(".bin"), path.with_suffix(".bin")), (staged, path)):
            atomic_write(dst, lambda f, src=src: f.write(src.read_bytes()))
    return path
