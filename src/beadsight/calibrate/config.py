"""Settings of ``beadsight calibrate``: :class:`CalibrateConfig` and the recipe's defaults.

The defaults were chosen by measurement on held-out simulated pouches with few presses
(docs/calibration.md, "How the recipe was chosen"). Imports neither torch nor numpy, so
the command line reads its defaults from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from beadsight.config import DEVICE_CHOICES, ConfigError, _Serializable, require_paths

DEFAULT_BUDGET_MIN = 10.0  # minutes for the whole calibration (evaluations included)
LAYER_CHOICES = ("decoder", "all", "none")  # none: only the zero-press alignment
CALIBRATION_SPLIT = (0.7, 0.1, 0.2)  # train / early stopping / test, by press
MIN_PRESSES = 3  # one press each to train on, to stop early on and to test on
RECOMMENDED_PRESSES = 10
MODEL_FILE, METRICS_FILE, REPORT_FILE = "model.pt", "metrics.json", "report.html"
ALIGNED_FILE = "aligned.pt"  # the base model after the zero-press alignment
TRAIN_FOLDER = "train"  # the fine-tuning's training run folder inside the output folder
CURVE_PLOT = "learning_curve.png"


@dataclass(frozen=True)
class CalibrateConfig(_Serializable):
    """Everything a calibration depends on; stored in the run's metrics.json."""

    data: str  # the new sensor's presses (HDF5, ours or the reference's layout)
    out: str  # output folder
    base: str | None = None  # checkpoint to start from; None: the shipped base model
    budget_min: float = DEFAULT_BUDGET_MIN  # wall clock for the whole calibration, minutes
    rest: str | None = None  # untouched-sensor frames (HDF5); None: the presses' pre-contact frames
    presses: int | None = None  # use this many presses (after skip); None: all
    skip: int = 0  # drop the first presses (a new pouch's break-in)
    gain: bool = False  # fit a per-sensor force gain on the training presses
    layers: str = "decoder"  # decoder (encoder fixed; measured best) | all | none (alignment)
    lr: float = 3e-4  # peak AdamW learning rate (cosine to lr_min over the budget)
    lr_min: float = 1e-5
    batch_size: int = 16
    augment: bool = False  # the 8 dihedral transforms (measured: worse on one pouch)
    noise_std: float = 0.05  # Gaussian input noise on the normalised frames
    val_every_min: float = 0.25  # validate on the early-stopping presses this often
    seed: int = 0  # split and batch order
    device: str = "auto"
    overwrite: bool = False  # replace the files of an earlier calibration in out
    progress: bool = True

    def __post_init__(self) -> None:
        require_paths(self, "data", "out")
        for name in ("budget_min", "lr", "val_every_min"):
            if not 0 < getattr(self, name) < math.inf:
                raise ConfigError(f"{name} must be finite and > 0, got {getattr(self, name)!r}")
        if self.presses is not None and self.presses < 1:
            raise ConfigError(f"presses must be >= 1, got {self.presses}")
        if self.skip < 0 or self.batch_size < 1:
            raise ConfigError(
                f"skip must be >= 0 and batch_size >= 1 ({self.skip}, {self.batch_size})"
            )
        if self.layers not in LAYER_CHOICES:
            raise ConfigError(f"layers must be one of {LAYER_CHOICES}, got {self.layers!r}")
        if not self.lr_min <= self.lr:
            raise ConfigError(f"lr_min ({self.lr_min}) must not exceed lr ({self.lr})")
        if self.device.split(":")[0] not in ("auto", "cpu", "cuda", "mps"):
            raise ConfigError(f"device must be {DEVICE_CHOICES}, got {self.device!r}")
