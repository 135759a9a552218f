"""Checkpoints: our self-describing format and the reference's training pickles, loaded safely.

:mod:`~beadsight.checkpoint.format` holds the format (:class:`PressureModel`,
:class:`CheckpointMeta`, :func:`save_checkpoint`) and the safe read of a checkpoint file;
:mod:`~beadsight.checkpoint.reference` imports the reference's pickles. :func:`load_checkpoint`
reads either, as data: nothing in a file is ever executed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from beadsight.checkpoint.format import (
    CheckpointError,
    CheckpointMeta,
    PressureModel,
    UnsafeCheckpointError,
    atomic_torch_save,
    looks_like_checkpoint,
    model_from,
    read_checkpoint_file,
    read_ours,
    save_checkpoint,
)
from beadsight.checkpoint.reference import read_reference

__all__ = [
    "CheckpointError",
    "CheckpointMeta",
    "PressureModel",
    "UnsafeCheckpointError",
    "atomic_torch_save",
    "averaged_from",
    "checkpoint_summary",
    "load_checkpoint",
    "looks_like_checkpoint",
    "read_checkpoint_file",
    "save_checkpoint",
]


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> PressureModel:
    """Load a beadsight checkpoint or a reference training checkpoint, safely.

    Never executes code from the file: a pickle that asks for anything other than
    tensors, plain values or plain numeric numpy arrays raises
    :class:`UnsafeCheckpointError`. Non-finite weights or statistics, a zero pixel_std,
    a non-positive output scale and metadata that does not fit the weights raise
    :class:`CheckpointError`, so no command runs a model that can only output NaN.
    """
    path = Path(path)
    obj = read_checkpoint_file(path)
    if "beadsight" in obj:
        meta, state = read_ours(obj, path)
    elif "model_state_dict" in obj:
        meta, state = read_reference(obj, path)
    else:
        raise CheckpointError(
            f"{path}: neither a beadsight checkpoint (no 'beadsight' entry) nor a reference "
            f"checkpoint (no 'model_state_dict'); keys: {sorted(map(str, obj))[:10]}"
        )
    return model_from(meta, state, path, map_location)


def averaged_from(provenance: dict[str, Any]) -> list[str] | None:
    """``path x weight`` of each checkpoint a `beadsight average` checkpoint is the mean of
    (None for any other checkpoint), read from its provenance."""
    average = provenance.get("average")
    if not isinstance(average, list):
        return None
    return [
        f"{e.get('path')} x {e.get('weight'):.3f}"
        for e in average
        if isinstance(e, dict) and isinstance(e.get("weight"), int | float)
    ]


def checkpoint_summary(path: str | Path) -> dict[str, Any]:
    """What a checkpoint is and how it was made: architecture, input, output, training."""
    model = load_checkpoint(path)
    meta, training = model.meta, model.meta.training
    init = meta.provenance.get("init")
    return {
        "path": str(path),
        "format": "reference" if meta.provenance.get("source") == "reference" else "beadsight",
        "parameters": sum(p.numel() for p in model.module.parameters()),
        **meta.model.to_dict(),
        "image_size_px": model.image_size,
        "channel_order": meta.channel_order,
        "output_scale_kpa": meta.output_scale_kpa,
        "dataset": meta.provenance.get("dataset") or meta.provenance.get("dataset_path"),
        "initialised_from": init.get("path") if isinstance(init, dict) else None,
        "averaged_from": averaged_from(meta.provenance),
        "step": training.get("step"),
        "epoch": training.get("epoch", meta.provenance.get("epoch")),
        "best_val": training.get("best_val"),
        "geometry": meta.geometry.to_dict(),
    }
