"""The one-time import of the reference's training checkpoints (pickled dicts).

A reference checkpoint is the dict its training script pickled with ``torch.save``:
``model_state_dict``, ``pixel_mean``/``pixel_std`` (BGR, 0..255), ``avg_pressure`` (Pa),
``window_size``, ``data_loader_info`` and the split (``train_indices``/``test_indices``),
with numpy arrays among the values. :func:`beadsight.checkpoint.format.read_checkpoint_file`
reads it as data (checked numpy stand-ins, never code); :func:`read_reference` turns it into
our :class:`~beadsight.checkpoint.format.CheckpointMeta` and checked weights, which
:func:`beadsight.checkpoint.load_checkpoint` builds like one of ours.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from beadsight.checkpoint.format import (
    CheckpointError,
    CheckpointMeta,
    checked_floats,
    checked_number,
    checked_weights,
)
from beadsight.config import REFERENCE_G_TO_N, SensorGeometry
from beadsight.geometry import PA_PER_KPA
from beadsight.model import infer_model_config


def reference_geometry(info: dict, path: Path) -> SensorGeometry:
    """Sensor geometry from a reference ``data_loader_info`` dict."""
    geometry = SensorGeometry().to_dict()
    try:
        if "image_size" in info:
            geometry["image_size_px"] = int(np.asarray(info["image_size"]).reshape(-1)[0])
        if "sensor_size" in info:
            geometry["sensor_size_mm"] = float(np.asarray(info["sensor_size"]).reshape(-1)[0])
        if "contact_radius" in info:
            geometry["finger_radius_mm"] = float(info["contact_radius"])
        return SensorGeometry.from_dict(geometry)
    except (ValueError, TypeError, IndexError) as e:
        raise CheckpointError(f"{path}: data_loader_info: {e}") from None


def read_reference(obj: dict[str, Any], path: Path) -> tuple[CheckpointMeta, dict]:
    """The metadata and checked weights of a reference training dict (BGR, 0..255
    mean/std, avg_pressure in Pa)."""
    for key in ("model_state_dict", "pixel_mean", "pixel_std", "avg_pressure"):
        if key not in obj:
            raise CheckpointError(f"{path}: reference checkpoint has no {key!r} entry")
    state = checked_weights(obj["model_state_dict"], path)
    dropout = checked_number(obj.get("dropout_prob", 0.2), path, "dropout_prob")
    try:
        model = infer_model_config(state, dropout=dropout)
    except (ValueError, IndexError) as e:
        raise CheckpointError(f"{path}: model_state_dict: {e}") from None
    if (
        "window_size" in obj
        and checked_number(obj["window_size"], path, "window_size") != model.frames
    ):
        raise CheckpointError(
            f"{path}: window_size is {obj['window_size']} but the weights take "
            f"{model.frames} frames"
        )
    info = obj.get("data_loader_info") or {}
    if not isinstance(info, dict):
        raise CheckpointError(
            f"{path}: data_loader_info is a {type(info).__name__}; expected a dict"
        )
    meta = CheckpointMeta(
        model=model,
        geometry=reference_geometry(info, path),
        pixel_mean=checked_floats(obj["pixel_mean"], path, "pixel_mean"),
        pixel_std=checked_floats(obj["pixel_std"], path, "pixel_std"),
        channel_order="BGR",
        output_scale_kpa=checked_number(obj["avg_pressure"], path, "avg_pressure") / PA_PER_KPA,
        provenance={
            "source": "reference",
            "file": str(path),
            "epoch": int(checked_number(obj["epoch"], path, "epoch")) if "epoch" in obj else None,
            "dataset_path": str(obj.get("dataset_path", "")),
            "force_unit": str(info.get("force_unit", "g")),
            "g_to_n": REFERENCE_G_TO_N,
        },
        training=reference_training(obj),
    )
    return meta, state


def reference_training(obj: dict[str, Any]) -> dict[str, Any]:
    """The reference's split: window-end frame indices into the file at dataset_path
    (read by ``evaluate --split test``); indices that are not integers are left out."""
    out: dict[str, Any] = {"dataset_path": str(obj.get("dataset_path", ""))}
    for key in ("train_indices", "test_indices"):
        try:
            values = np.asarray(obj[key], dtype=np.float64).reshape(-1)
        except (KeyError, TypeError, ValueError):
            continue
        if np.isfinite(values).all() and np.array_equal(values, np.round(values)):
            out[key] = values.astype(np.int64).tolist()
    return out
