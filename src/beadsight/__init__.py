"""beadsight: toolkit for the BeadSight visuo-tactile sensor."""

from beadsight.checkpoint import CheckpointError, PressureModel, load_checkpoint, save_checkpoint
from beadsight.config import ContactThresholds, ModelConfig, SensorGeometry

__version__ = "0.1.0"

__all__ = [
    "CheckpointError",
    "ContactThresholds",
    "ModelConfig",
    "PressureModel",
    "SensorGeometry",
    "__version__",
    "load_checkpoint",
    "save_checkpoint",
]
