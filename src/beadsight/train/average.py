"""Weight averaging of checkpoints of one model (a "model soup").

Two runs of one model that share their start (a fine-tune and the checkpoint it began
from, say) can be averaged weight by weight; the average can read new presses better than
either (the shipped sim model is such an average), at no cost when it runs. Only
checkpoints of the same network, geometry and normalisation are averaged: anything else
is refused by name.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import torch

from beadsight.checkpoint import CheckpointError, PressureModel, load_checkpoint
from beadsight.errors import ConfigError

# Metadata that must match for the weights to mean the same thing in every checkpoint.
SAME_META = ("model", "geometry", "pixel_mean", "pixel_std", "channel_order", "output_scale_kpa")


def average_checkpoints(
    paths: Sequence[str | Path], weights: Sequence[float] | None = None
) -> PressureModel:
    """The weighted mean of the weights of the checkpoints at ``paths`` (at least two):
    ``weights`` (default equal) are relative, so they are divided by their sum. The result
    keeps the first checkpoint's metadata, its provenance replaced by the averaged
    checkpoints' (path, weight and their own provenance) and its training record emptied."""
    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise ConfigError(f"average: give at least two checkpoints, got {len(paths)}")
    weights = [1.0] * len(paths) if weights is None else [float(w) for w in weights]
    if len(weights) != len(paths):
        raise ConfigError(
            f"average: {len(weights)} weights for {len(paths)} checkpoints; give one per checkpoint"
        )
    if not all(math.isfinite(w) and w > 0 for w in weights):
        raise ConfigError(f"average: weights must be finite and > 0, got {weights}")
    total = sum(weights)
    weights = [w / total for w in weights]
    models = [load_checkpoint(p) for p in paths]
    first = models[0]
    for path, model in zip(paths[1:], models[1:], strict=True):
        for name in SAME_META:
            if getattr(model.meta, name) != getattr(first.meta, name):
                raise CheckpointError(
                    f"{path}: its {name} differs from {paths[0]}'s; only checkpoints of one "
                    "model (the same network, geometry and normalisation) can be averaged"
                )
    states = [m.module.net.state_dict() for m in models]
    mean = {}
    for key, tensor in states[0].items():
        if not tensor.is_floating_point():
            mean[key] = tensor
            continue
        total_t = sum(w * s[key].to(torch.float64) for w, s in zip(weights, states, strict=True))
        mean[key] = total_t.to(tensor.dtype)
    provenance = {
        "average": [
            {"path": str(p), "weight": w, "provenance": m.meta.provenance}
            for p, w, m in zip(paths, weights, models, strict=True)
        ]
    }
    meta = dataclasses.replace(first.meta, provenance=provenance, training={})
    out = PressureModel.create(meta)
    out.module.net.load_state_dict(mean)
    return out
