"""beadsight: toolkit for the BeadSight visuo-tactile sensor.

The public API is imported lazily (PEP 562) so that light tools (device
drivers, the CLI's help) start without loading torch.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_API = {  # name -> the module that defines it; each line says what the name is
    # checkpoints and the model
    "CheckpointError": "beadsight.checkpoint",  # a checkpoint is missing, unsafe or unfit
    "PressureModel": "beadsight.checkpoint",  # a loaded model: frames in, kPa maps out
    "load_checkpoint": "beadsight.checkpoint",  # a beadsight or reference checkpoint, safely
    "save_checkpoint": "beadsight.checkpoint",  # weights + self-describing metadata, atomically
    # configuration (frozen dataclasses, units in field names)
    "ContactThresholds": "beadsight.config",  # force hysteresis between presses, N
    "ModelConfig": "beadsight.config",  # the U-Net: frames (T), frame_stride, width, ...
    "SensorGeometry": "beadsight.config",  # field of view (mm), image size (px), finger radius
    # running a model
    "PressurePredictor": "beadsight.inference.predictor",  # frame by frame -> PressureReading
    "PressureReading": "beadsight.inference.predictor",  # kPa map, force N, CoP mm, contact
    "PredictorSettings": "beadsight.inference.predictor",  # gap policy and contact rules
    "create_backend": "beadsight.inference.select",  # a runtime by name, or "auto"
    "export_model": "beadsight.inference.export",  # ONNX / OpenVINO file, checked against torch
    "resolve_device": "beadsight.torch_device",  # the one device rule ("auto": CUDA, else CPU)
    # data, evaluation, live sensing
    "open_dataset": "beadsight.data.dataset",  # a beadsight or reference HDF5 dataset
    "predict_recording": "beadsight.evaluation.predict",  # kPa maps for a dataset or video
    "LiveSensor": "beadsight.live.sensor",  # camera / video / simulator -> readings, threaded
    "LiveSettings": "beadsight.live.settings",  # how LiveSensor runs
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
