"""The models shipped in the package's ``assets`` folder, and finding them."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from beadsight.checkpoint import CheckpointError

SHIPPED_MODEL = "sim_model.pt"  # the simulated-sensor model, in the package's assets folder
BASE_MODEL = "base_model.pt"  # the any-pouch base model that `calibrate` fine-tunes (assets)


def shipped_model_path(name: str | None = None) -> Path:
    """Path of a model shipped with the package (default ``SHIPPED_MODEL``, the simulated
    sensor's; ``BASE_MODEL``: the any-pouch base); :class:`CheckpointError` if absent."""
    name = name or SHIPPED_MODEL
    path = Path(str(importlib.resources.files("beadsight").joinpath("assets", name)))
    if not path.is_file():
        raise CheckpointError(
            f"the shipped model {path} is missing from this install; pass --checkpoint PATH "
            "(a model trained with `beadsight train`, or `beadsight demo --train`)"
        )
    return path
