"""What a training run depends on: :class:`TrainConfig`, and how it is resolved from
code defaults, the resumed run's ``config.json``, a TOML file and CLI flags.

Imports neither torch nor numpy, so the command line reads its defaults from here
without loading them.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from beadsight.config import (
    DEFAULT_SPLIT_FRACTIONS,
    DEVICE_CHOICES,
    ConfigError,
    ModelConfig,
    _Serializable,
    load_toml,
    require_paths,
)
from beadsight.files import read_json_object

CONFIG_FILE = "config.json"  # the resolved TrainConfig in the run folder
PRECISIONS = ("fp32", "bf16", "fp16")
SIZE_MULTIPLE = 8  # the U-Net halves the image three times
LR_SCHEDULES = ("constant", "cosine")
LOADER_MODES = ("auto", "host", "device")
TRAIN_LAYERS = ("all", "decoder")  # which U-Net layers an optimizer step changes
# Fields a resumed run must share with the run it continues (others, e.g. steps, may change).
RESUME_FIXED_FIELDS = (
    "frames",
    "frame_stride",
    "width",
    "up_kernel",
    "dropout",
    "image_size",
    "split",
    "seed",
    "batch_size",
    "lr",
    "lr_schedule",
    "lr_min",
    "weight_decay",
    "noise_std",
    "presses",
    "skip_presses",
    "train_layers",
    "augment",
    "rest_input",
    "rest_norm",
    "color_jitter",
    "qat",
)
# Settings read from the ``init`` checkpoint when neither the TOML file nor a flag sets them.
INIT_MODEL_FIELDS = ("frames", "frame_stride", "width", "up_kernel", "rest_input", "rest_norm")
# Of those, the ones the weights' shapes fix (a run may change the stride of its init).
INIT_SHAPE_FIELDS = ("frames", "width", "up_kernel", "rest_input")
_INT_MINIMUMS = {
    "epochs": 1,
    "batch_size": 1,
    "num_workers": 0,
    "log_every_steps": 1,
    "checkpoint_every_steps": 1,
    "val_stride": 1,
    "seed": 0,
    "skip_presses": 0,
}
_OPTIONAL_INTS = ("steps", "threads", "image_size", "presses")  # None, or an integer >= 1
_NON_NEGATIVE = (
    "lr",
    "lr_min",
    "weight_decay",
    "noise_std",
    "checkpoint_every_min",
    "color_jitter",
)
_OPTIONAL_POSITIVE = ("budget_min", "val_every_min")  # None, or a number > 0


@dataclass(frozen=True)
class TrainConfig(_Serializable):
    """Everything a training run depends on; stored as the run's config.json."""

    data: str  # dataset file (HDF5)
    out: str  # run folder
    steps: int | None = None  # optimizer steps in total; None: train for ``epochs``
    epochs: int = 100  # passes over the training windows (used when steps is None)
    budget_min: float | None = None  # wall-clock budget in minutes (validation included):
    # the run stops at the budget or at steps/epochs, whichever comes first
    batch_size: int = 64  # windows per optimizer step, over all DDP processes together
    lr: float = 1e-4  # AdamW learning rate (the peak one under a schedule)
    lr_schedule: str = "constant"  # constant | cosine (from lr down to lr_min over the run)
    lr_min: float = 0.0  # the cosine schedule's final learning rate
    init: str | None = None  # checkpoint whose weights start the run (fine-tuning)
    weight_decay: float = 1e-4  # AdamW decoupled weight decay
    dropout: float = 0.2  # conv-block dropout
    width: int = 16  # U-Net channels of the first block
    frames: int = 15  # T: frames the network sees per prediction
    frame_stride: int = 1  # those frames are this many camera frames apart
    up_kernel: int = 1  # U-Net up-conv kernel (1 = reference weights, 3 = paper text)
    image_size: int | None = None  # train at this size (px, multiple of 8); None: the dataset's
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    precision: str = "fp32"  # fp32 | bf16 (autocast) | fp16 (autocast + GradScaler, CUDA only)
    seed: int = 0  # split, initialisation, batch order, augmentation
    noise_std: float = 0.05  # Gaussian input noise on the normalised frames (training only)
    split: tuple[float, float, float] = DEFAULT_SPLIT_FRACTIONS  # train, val, test fractions
    resume: bool = False  # continue the run in ``out`` from its last.pt
    loader: str = "auto"  # auto | host (DataLoader workers) | device (frames on the device)
    num_workers: int = 2  # DataLoader workers in host loader mode
    threads: int | None = None  # torch CPU threads (None: the faster of torch's default and 1)
    log_every_steps: int = 50  # a metrics.jsonl line every this many steps
    checkpoint_every_steps: int = 1000  # also save last.pt every this many steps
    checkpoint_every_min: float = 10.0  # ... and at least this often (minutes)
    val_stride: int = 1  # validate on every val_stride-th window (1: all)
    val_every_min: float | None = None  # also validate (best.pt) this often; None: per epoch
    val_at_start: bool = False  # validate the initial weights too (best.pt may be them)
    presses: int | None = None  # use only this many presses of the dataset (None: all)
    skip_presses: int = 0  # ... after dropping its first ones (a new pouch's break-in)
    train_layers: str = "all"  # all | decoder (the encoder stays as initialised)
    augment: bool = True  # the 8 dihedral transforms of the training windows
    rest_input: bool = False  # rest-referenced model: it also sees the pouch at rest
    rest_norm: bool = False  # ... normalised by the rest image's own contrast (ModelConfig)
    color_jitter: float = 0.0  # strength of random colour/contrast changes (0: none; 1: strong)
    qat: bool = False  # quantization-aware: train through int8 fake quantizers
    progress: bool = True  # tqdm progress bars

    def __post_init__(self) -> None:
        require_paths(self, "data", "out")
        if self.init is not None:
            object.__setattr__(self, "init", str(self.init))
        self._check_numbers()
        self._check_choices()
        object.__setattr__(self, "split", _check_split(self.split))
        self.model_config()  # validates width, frames, up_kernel, dropout

    def _check_numbers(self) -> None:
        for name, minimum in _INT_MINIMUMS.items():
            _check_int(self, name, minimum)
        for name in _OPTIONAL_INTS:
            if getattr(self, name) is not None:
                _check_int(self, name, 1)
        for name in _NON_NEGATIVE:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value >= 0:
                raise ConfigError(f"{name} must be a number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in _OPTIONAL_POSITIVE:
            value = getattr(self, name)
            if value is not None:
                if isinstance(value, bool) or not isinstance(value, numbers.Real):
                    raise ConfigError(f"{name} must be a number > 0, got {value!r}")
                if not 0 < value < math.inf:
                    raise ConfigError(f"{name} must be finite and > 0, got {value!r}")
                object.__setattr__(self, name, float(value))
        if not self.lr > 0:
            raise ConfigError(f"lr must be > 0, got {self.lr}")
        if self.lr_min > self.lr:
            raise ConfigError(f"lr_min ({self.lr_min}) must not exceed lr ({self.lr})")
        if self.image_size is not None and self.image_size % SIZE_MULTIPLE:
            raise ConfigError(
                f"image_size must be a multiple of {SIZE_MULTIPLE} (the U-Net halves it three "
                f"times), got {self.image_size}"
            )

    def _check_choices(self) -> None:
        for name, choices in (
            ("lr_schedule", LR_SCHEDULES),
            ("precision", PRECISIONS),
            ("loader", LOADER_MODES),
            ("train_layers", TRAIN_LAYERS),
        ):
            if getattr(self, name) not in choices:
                raise ConfigError(f"{name} must be one of {choices}, got {getattr(self, name)!r}")
        if not re.fullmatch(r"auto|cpu|mps|cuda(:\d+)?", str(self.device)):
            raise ConfigError(f"device must be {DEVICE_CHOICES}, got {self.device!r}")
        if self.precision == "fp16" and self.device == "cpu":
            raise ConfigError("precision fp16 needs a CUDA device; use bf16 or fp32 on cpu")

    def model_config(self) -> ModelConfig:
        return ModelConfig(
            frames=self.frames,
            frame_stride=self.frame_stride,
            width=self.width,
            up_kernel=self.up_kernel,
            dropout=self.dropout,
            rest_input=self.rest_input,
            rest_norm=self.rest_norm,
        )

    @property
    def span(self) -> int:
        """Consecutive frames one training window covers (the model config's span)."""
        return self.model_config().span

    def learning_rate(self, step: int, total_steps: int, progress: float | None = None) -> float:
        """The learning rate of optimizer step ``step`` (0-based) of ``total_steps``, or at
        ``progress`` (0..1: the share of a wall-clock budget spent) when given."""
        if self.lr_schedule == "constant":
            return self.lr
        if progress is None:
            if total_steps <= 1:
                return self.lr
            progress = min(step, total_steps - 1) / (total_steps - 1)
        progress = min(max(progress, 0.0), 1.0)
        return self.lr_min + 0.5 * (self.lr - self.lr_min) * (1.0 + math.cos(math.pi * progress))


def _check_int(config: TrainConfig, name: str, minimum: int) -> None:
    value = getattr(config, name)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    object.__setattr__(config, name, int(value))


def _check_split(split: Any) -> tuple[float, float, float]:
    values = tuple(split) if isinstance(split, (list, tuple)) else None
    if (
        values is None
        or len(values) != 3
        or not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in values)
        or min(values) < 0
        or not math.isclose(sum(values), 1.0, abs_tol=1e-6)
    ):
        raise ConfigError(
            f"split must be three fractions (train, val, test) >= 0 summing to 1, got {split!r}"
        )
    return tuple(float(v) for v in values)  # type: ignore[return-value]


def field_default(name: str) -> Any:
    """The code default of TrainConfig field ``name``."""
    return TrainConfig.__dataclass_fields__[name].default


def resolve_train_config(
    overrides: Mapping[str, Any], config_file: str | Path | None = None
) -> TrainConfig:
    """Merge configuration: code defaults < the run's config.json (when resuming) <
    the TOML file (flat keys or a ``[train]`` table) < ``overrides`` (CLI flags; None
    values mean "not given"). With ``init`` (and not resuming), the model settings
    neither the file nor a flag gives come from that checkpoint."""
    names = {f.name for f in fields(TrainConfig)}
    file_values: dict[str, Any] = {}
    if config_file is not None:
        raw = load_toml(config_file)
        file_values = raw["train"] if isinstance(raw.get("train"), dict) else raw
        unknown = sorted(set(file_values) - names)
        if unknown:
            raise ConfigError(
                f"{config_file}: unknown training setting(s) {unknown}; known: {sorted(names)}"
            )
    given = {k: v for k, v in overrides.items() if v is not None}
    unknown = sorted(set(given) - names)
    if unknown:
        raise ConfigError(f"unknown training setting(s) {unknown}")
    values = _stored_config({**file_values, **given}, names)
    values.update(file_values)
    values.update(given)
    if values.get("init") and not values.get("resume"):
        from beadsight.checkpoint import load_checkpoint

        init_model = load_checkpoint(values["init"]).meta.model
        for name in INIT_MODEL_FIELDS:
            if name not in file_values and name not in given:
                values[name] = getattr(init_model, name)
    for required in ("data", "out"):
        if values.get(required) is None:
            raise ConfigError(
                f"{required}: required (--{required} or '{required}' in the config file)"
            )
    return TrainConfig.from_dict(values)


def _stored_config(early: Mapping[str, Any], names: set[str]) -> dict[str, Any]:
    """The settings of the run being resumed (its config.json), if ``early`` resumes one."""
    if not (early.get("resume") and early.get("out")):
        return {}
    stored = Path(str(early["out"])) / CONFIG_FILE
    if not stored.is_file():
        return {}
    data = read_json_object(stored, ConfigError, "a JSON object of training settings")
    return {k: v for k, v in data.items() if k in names}
