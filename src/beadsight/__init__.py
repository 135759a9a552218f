"""beadsight: toolkit for the BeadSight visuo-tactile sensor.

The public API is imported lazily (PEP 562) so that light tools (device
drivers, the CLI's help) start without loading torch.
"""

from __future__ import annotations

import importlib
from typing import Any

from beadsight import _compat

__version__ = "0.1.0"

_compat.install()  # old module paths (beadsight.predictor, ...) still import, with a warning


_API = {
    "CheckpointError": "beadsight.checkpoint",
    "PressureModel": "beadsight.checkpoint",
    "load_checkpoint": "beadsight.checkpoint",
    "save_checkpoint": "beadsight.checkpoint",
    "ContactThresholds": "beadsight.config",
    "ModelConfig": "beadsight.config",
    "SensorGeometry": "beadsight.config",
    "PressurePredictor": "beadsight.inference.predictor",
    "Reading": "beadsight.inference.predictor",
    "open_dataset": "beadsight.data.dataset",
    "predict_recording": "beadsight.evaluation.predict",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'beadsight' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
