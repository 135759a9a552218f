"""Settings of ``beadsight calibrate``: :class:`CalibrateConfig` and the recipe's defaults.

The defaults were chosen by measurement on held-out simulated pouches with few presses
(docs/calibration.md, "How the recipe was chosen"). Imports neither torch nor numpy, so
the command line reads its defaults from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from beadsight.config import DEVICE_CHOICES, ConfigError, _Serializable

DEFAULT_BUDGET_MIN = 10.0  # minutes for the whole calibration (evaluations included)
# The smallest budget in which a fine-tuning candidate gets any training on a 2-core CPU
# with the shipped base model and 30 presses (measured: none at 1 min, 9 steps at 1.5 min;
# docs/calibration.md, "Budgets"); below it only zero-shot and zero-press are scored.
SMALLEST_USEFUL_BUDGET_MIN = 1.5
# The candidates, in the order they are tried (docs/calibration.md, "Candidates"):
# zero-press: the base model with the new pouch's rest statistics (no press used);
# decoder / all: fine-tune those layers of the base; scratch: a small model from scratch.
CANDIDATES = ("zero-press", "decoder", "all", "scratch")
FINE_TUNED = ("decoder", "all", "scratch")
# Each fine-tuning candidate's share of the training time left after the evaluations.
CANDIDATE_SHARES = {"decoder": 1.0, "all": 1.0, "scratch": 1.0}
SCRATCH_MIN_TRAIN_PRESSES = 8  # fewer training presses cannot train a model from scratch
SCRATCH_WIDTH = 8  # the small model trained from scratch (issue 24's winning command)
SCRATCH_LR = 1e-3
MIN_CANDIDATE_S = 30.0  # a fine-tuning candidate given less training time than this is skipped
# (measured: at 5 s, a 2-min budget split three ways bought 1-3 steps per candidate)
# train / early stopping / test, by press. Early stopping also chooses the kept candidate:
# with 30 presses, 6 choose where 3 chose wrongly (docs/calibration.md, "Choosing on 6
# presses"); its own test presses (3) are a check, a second session the firmer one.
CALIBRATION_SPLIT = (0.7, 0.2, 0.1)
MIN_PRESSES = 3  # one press each to train on, to stop early on and to test on
RECOMMENDED_PRESSES = 10
MODEL_FILE, METRICS_FILE, REPORT_FILE = "model.pt", "metrics.json", "report.html"
ALIGNED_FILE = "aligned.pt"  # the zero-press candidate: the base with the rest statistics
REST_FILE = "rest.npz"  # the new pouch's rest reference (the format of live --rest)
TRAIN_FOLDER = "train"  # the fine-tuning runs' folder inside the output folder (one per candidate)
CURVE_PLOT = "learning_curve.png"


@dataclass(frozen=True)
class CalibrateConfig(_Serializable):
    """Everything a calibration depends on; stored in the run's metrics.json."""

    data: str | None  # the new sensor's presses (HDF5, ours or the reference's layout)
    out: str  # output folder
    base: str | None = None  # checkpoint to start from; None: the shipped base model
    budget_min: float = DEFAULT_BUDGET_MIN  # wall clock for the whole calibration, minutes
    rest: str | None = None  # the rest file (.npz); None: the presses' pre-contact frames
    presses: int | None = None  # use this many presses (after skip); 0: rest frames only
    skip: int = 0  # drop the first presses (a new pouch's break-in)
    gain: bool = False  # fit a per-sensor force gain on the training presses
    candidates: tuple[str, ...] = CANDIDATES  # the ones tried where they make sense
    lr: float = 3e-4  # peak AdamW learning rate of fine-tuning (cosine to lr_min)
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
        for name in ("data", "out", "rest", "base"):
            value = getattr(self, name)
            if value is not None and not str(value):
                raise ConfigError(f"{name} must be a path, got {value!r}")
            if value is not None:
                object.__setattr__(self, name, str(value))
        if self.out is None:
            raise ConfigError("out must be a path, got None")
        if self.data is None and not (self.presses == 0 and self.rest):
            raise ConfigError(
                "calibrate needs --data (the new pouch's presses), or --presses 0 with "
                "--rest FILE (a rest file of the untouched pouch)"
            )
        for name in ("budget_min", "lr", "val_every_min"):
            if not 0 < getattr(self, name) < math.inf:
                raise ConfigError(f"{name} must be finite and > 0, got {getattr(self, name)!r}")
        if self.presses is not None and self.presses < 0:
            raise ConfigError(f"presses must be >= 0, got {self.presses}")
        if self.skip < 0 or self.batch_size < 1:
            raise ConfigError(
                f"skip must be >= 0 and batch_size >= 1 ({self.skip}, {self.batch_size})"
            )
        object.__setattr__(self, "candidates", tuple(self.candidates))
        unknown = [c for c in self.candidates if c not in CANDIDATES]
        if unknown or not self.candidates or len(set(self.candidates)) < len(self.candidates):
            raise ConfigError(
                f"candidates must be one or more of {CANDIDATES} (each once), "
                f"got {list(self.candidates)}"
            )
        if not self.lr_min <= self.lr:
            raise ConfigError(f"lr_min ({self.lr_min}) must not exceed lr ({self.lr})")
        if self.device.split(":")[0] not in ("auto", "cpu", "cuda", "mps"):
            raise ConfigError(f"device must be {DEVICE_CHOICES}, got {self.device!r}")

    @property
    def zero_press(self) -> bool:
        """``presses 0``: calibrate from rest frames only."""
        return self.presses == 0
