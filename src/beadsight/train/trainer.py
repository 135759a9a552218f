"""Training the BeadSight U-Net: ``train(TrainConfig(data=..., out=...)) -> run folder``.

Reference recipe (defaults): AdamW (lr 1e-4, weight decay 1e-4), batch 64, dropout
0.2, Gaussian input noise (std 0.05 on the normalised frames, training only), all 8
dihedral transforms, MSE on the normalised map ``target_kpa / output_scale_kpa``,
presses split 70/10/20 by a seeded shuffle.

Normalisation is measured on the training split at the training image size:
``pixel_mean``/``pixel_std`` per RGB channel in 0..255 units, and
``output_scale_kpa`` as the reference's ``avg_pressure``: the pressure of the finger
disk carrying the mean in-contact force, averaged over the whole image, i.e.
``disk_pressure(F_mean) * disk_pixels / S^2`` (see :func:`output_scale_kpa`).

The run folder (``config.out``)::

    config.json    the resolved TrainConfig
    split.json     press ids per split, split fractions/seed, dataset path + fingerprint
    metrics.jsonl  one JSON object per log event (same keys on every line)
    last.pt        newest checkpoint with the full training state (resume from it)
    best.pt        lowest validation loss (model + metadata only)

Learning rate: constant (the reference), or ``lr_schedule="cosine"``, decaying from
``lr`` to ``lr_min`` over the run's total steps. ``init`` starts the weights from an
existing checkpoint (fine-tuning, e.g. the shipped simulated-sensor model on a real
sensor's data); the run then keeps that checkpoint's normalisation and output scale,
which its weights were trained for.

Checkpoints are written atomically every epoch, every ``checkpoint_every_steps``
steps and every ``checkpoint_every_min`` minutes, so a killed run loses little;
``resume=True`` continues from ``last.pt`` with the same split, optimizer state,
step count and batch order. Under ``torchrun`` (``WORLD_SIZE`` > 1) training is
data-parallel (DDP; NCCL on GPUs, gloo on CPUs): windows are sharded like
``DistributedSampler``, ``batch_size`` is the global batch, and only rank 0 writes.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
import time
from collections.abc import Mapping
from contextlib import nullcontext
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as torch_dist
import torch.nn.functional as F
from tqdm import tqdm

from beadsight import __version__
from beadsight.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    PressureModel,
    load_checkpoint,
    read_checkpoint_file,
)
from beadsight.config import (
    ConfigError,
    ModelConfig,
    SensorGeometry,
    _Serializable,
    load_toml,
    renamed_fields,
)
from beadsight.data.dataset import Dataset, DatasetError, open_dataset
from beadsight.data.splits import DEFAULT_FRACTIONS, SPLITS, split_presses, window_ends
from beadsight.errors import BeadSightError
from beadsight.geometry import disk_maps
from beadsight.torch_device import DEVICE_CHOICES, resolve_device
from beadsight.train.windows import (
    LOADER_MODES,
    DeviceFrames,
    DeviceWindows,
    WindowDataset,
    WindowLabels,
    WindowLoader,
    batches_per_epoch,
    choose_loader_mode,
    dataset_fingerprint,
    pixel_stats,
    window_frame_mask,
)

logger = logging.getLogger(__name__)

PRECISIONS = ("fp32", "bf16", "fp16")
SIZE_MULTIPLE = 8  # the U-Net halves the image three times
CONFIG_FILE, SPLIT_FILE, METRICS_FILE = "config.json", "split.json", "metrics.jsonl"
LAST_CHECKPOINT, BEST_CHECKPOINT = "last.pt", "best.pt"
METRIC_KEYS = (
    "event",
    "step",
    "epoch",
    "train_loss",
    "val_loss",
    "val_mae_kpa",
    "samples_per_s",
    "lr",
    "time_s",
    "wall_time",
)
# Fields a resumed run must share with the run it continues (others, e.g. steps, may change).
MAX_LOG_INTERVAL_S = 60.0  # single-process runs also log at least this often
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
)
LR_SCHEDULES = ("constant", "cosine")
# Settings read from the ``init`` checkpoint when neither the TOML file nor a flag sets them.
INIT_MODEL_FIELDS = ("frames", "frame_stride", "width", "up_kernel")
# Of those, the ones the weights' shapes fix (a run may change the stride of its init).
INIT_SHAPE_FIELDS = ("frames", "width", "up_kernel")


@renamed_fields(window="frames")
@dataclass(frozen=True)
class TrainConfig(_Serializable):
    """Everything a training run depends on; stored as the run's config.json."""

    data: str  # dataset file (HDF5)
    out: str  # run folder
    steps: int | None = None  # optimizer steps in total; None: train for ``epochs``
    epochs: int = 100  # passes over the training windows (used when steps is None)
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
    split: tuple[float, float, float] = DEFAULT_FRACTIONS  # train, val, test fractions of presses
    resume: bool = False  # continue the run in ``out`` from its last.pt
    loader: str = "auto"  # auto | host (DataLoader workers) | device (frames on the device)
    num_workers: int = 2  # DataLoader workers in host loader mode
    threads: int | None = None  # torch CPU threads (None: torch's default)
    log_every_steps: int = 50  # a metrics.jsonl line every this many steps
    checkpoint_every_steps: int = 1000  # also save last.pt every this many steps
    checkpoint_every_min: float = 10.0  # ... and at least this often (minutes)
    val_stride: int = 1  # validate on every val_stride-th window (1: all)
    progress: bool = True  # tqdm progress bars

    def __post_init__(self) -> None:
        for name in ("data", "out"):
            value = getattr(self, name)
            if not isinstance(value, (str, os.PathLike)) or not str(value):
                raise ConfigError(f"{name} must be a path, got {value!r}")
            object.__setattr__(self, name, str(value))
        _check_int(self, "epochs", 1)
        _check_int(self, "batch_size", 1)
        _check_int(self, "num_workers", 0)
        _check_int(self, "log_every_steps", 1)
        _check_int(self, "checkpoint_every_steps", 1)
        _check_int(self, "val_stride", 1)
        _check_int(self, "seed", 0)
        for name in ("steps", "threads", "image_size"):
            if getattr(self, name) is not None:
                _check_int(self, name, 1)
        for name in ("lr", "lr_min", "weight_decay", "noise_std", "checkpoint_every_min"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
                raise ConfigError(f"{name} must be a number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        if not self.lr > 0:
            raise ConfigError(f"lr must be > 0, got {self.lr}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ConfigError(
                f"lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}"
            )
        if self.lr_min > self.lr:
            raise ConfigError(f"lr_min ({self.lr_min}) must not exceed lr ({self.lr})")
        if self.init is not None:
            object.__setattr__(self, "init", str(self.init))
        if self.image_size is not None and self.image_size % SIZE_MULTIPLE:
            raise ConfigError(
                f"image_size must be a multiple of {SIZE_MULTIPLE} (the U-Net halves it three "
                f"times), got {self.image_size}"
            )
        if self.precision not in PRECISIONS:
            raise ConfigError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if not re.fullmatch(r"auto|cpu|mps|cuda(:\d+)?", str(self.device)):
            raise ConfigError(f"device must be {DEVICE_CHOICES}, got {self.device!r}")
        if self.precision == "fp16" and self.device == "cpu":
            raise ConfigError("precision fp16 needs a CUDA device; use bf16 or fp32 on cpu")
        if self.loader not in LOADER_MODES:
            raise ConfigError(f"loader must be one of {LOADER_MODES}, got {self.loader!r}")
        split = tuple(self.split) if isinstance(self.split, (list, tuple)) else None
        if (
            split is None
            or len(split) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in split)
            or min(split) < 0
            or not math.isclose(sum(split), 1.0, abs_tol=1e-6)
        ):
            raise ConfigError(
                f"split must be three fractions (train, val, test) >= 0 summing to 1, got {self.split!r}"
            )
        object.__setattr__(self, "split", tuple(float(v) for v in split))
        self.model_config()  # validates width, frames, up_kernel, dropout

    def model_config(self) -> ModelConfig:
        return ModelConfig(
            frames=self.frames,
            frame_stride=self.frame_stride,
            width=self.width,
            up_kernel=self.up_kernel,
            dropout=self.dropout,
        )

    @property
    def span(self) -> int:
        """Consecutive frames one training window covers (the model config's span)."""
        return self.model_config().span

    def learning_rate(self, step: int, total_steps: int) -> float:
        """The learning rate of optimizer step ``step`` (0-based) of ``total_steps``."""
        if self.lr_schedule == "constant" or total_steps <= 1:
            return self.lr
        progress = min(step, total_steps - 1) / (total_steps - 1)
        return self.lr_min + 0.5 * (self.lr - self.lr_min) * (1.0 + math.cos(math.pi * progress))


def _check_int(config: TrainConfig, name: str, minimum: int) -> None:
    value = getattr(config, name)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    object.__setattr__(config, name, int(value))


def resolve_train_config(
    overrides: Mapping[str, Any], config_file: str | Path | None = None
) -> TrainConfig:
    """Merge configuration: code defaults < the run's config.json (when resuming) <
    the TOML file (flat keys or a ``[train]`` table) < ``overrides`` (CLI flags; None
    values mean "not given")."""
    names = {f.name for f in fields(TrainConfig)}
    file_values: dict[str, Any] = {}
    if config_file is not None:
        raw = load_toml(config_file)
        file_values = raw["train"] if isinstance(raw.get("train"), dict) else raw
        file_values = TrainConfig.upgrade_keys(file_values, source=str(config_file))
        unknown = sorted(set(file_values) - names)
        if unknown:
            raise ConfigError(
                f"{config_file}: unknown training setting(s) {unknown}; known: {sorted(names)}"
            )
    given = {k: v for k, v in overrides.items() if v is not None}
    given = TrainConfig.upgrade_keys(given, source="training settings")
    unknown = sorted(set(given) - names)
    if unknown:
        raise ConfigError(f"unknown training setting(s) {unknown}")
    values: dict[str, Any] = {}
    early = {**file_values, **given}
    stored = Path(str(early.get("out", ""))) / CONFIG_FILE
    if early.get("resume") and early.get("out") and stored.is_file():
        try:
            stored_values = TrainConfig.upgrade_keys(json.loads(stored.read_text()))
            values.update({k: v for k, v in stored_values.items() if k in names})
        except json.JSONDecodeError as e:
            raise ConfigError(f"{stored}: not valid JSON ({e})") from None
    values.update(file_values)
    values.update(given)
    if values.get("init") and not values.get("resume"):
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


# --- normalisation ------------------------------------------------------------------
def output_scale_kpa(contact_force_n: np.ndarray, geometry: SensorGeometry) -> float:
    """The reference ``avg_pressure`` in kPa: the finger disk carrying the mean in-contact
    force, averaged over the whole S x S image = ``disk_pressure(F_mean) * disk_pixels / S^2``
    (``disk_pixels``: the anti-aliased disk's area in pixels). Targets are divided by it
    so the network's outputs are O(1)."""
    force = np.asarray(contact_force_n, dtype=np.float64)
    if len(force) == 0 or not np.mean(force) > 0:
        raise DatasetError("no in-contact training frames: cannot set the output scale")
    disk = disk_maps(np.array([force.mean()]), np.zeros((1, 2)), geometry)[0]
    return float(disk.mean(dtype=np.float64))


def model_inputs(module, frames: torch.Tensor, noise_std: float = 0.0) -> torch.Tensor:
    """(B, T, S, S, 3) uint8 RGB -> (B, 3T, S, S) float32 normalised network input,
    plus Gaussian noise of ``noise_std`` (pass 0 for validation and inference)."""
    x = module.normalize(frames)
    if noise_std > 0:
        x = x + noise_std * torch.randn_like(x)
    return x


def autocast(device: torch.device, dtype: torch.dtype | None):
    """Autocast to ``dtype`` (bf16/fp16) on ``device``'s type; None: a no-op context."""
    if dtype is None:
        return nullcontext()
    return torch.autocast(torch.device(device).type, dtype=dtype)


def optimizer_step(
    module,
    net: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    frames: torch.Tensor,
    targets: torch.Tensor,
    *,
    output_scale_kpa: float,
    noise_std: float,
    autocast_dtype: torch.dtype | None = None,
    scaler: torch.amp.GradScaler | None = None,
) -> torch.Tensor:
    """One training step; returns the (detached, not synchronised) loss.

    module: the FramesToPressure (normalisation); net: its U-Net, or the U-Net
    wrapped in DDP. frames: (B, T, S, S, 3) uint8 RGB; targets: (B, S, S) kPa.
    Loss: MSE between the network output and ``targets / output_scale_kpa``.
    """
    x = model_inputs(module, frames, noise_std)
    with autocast(frames.device, autocast_dtype):
        out = net(x)  # (B, 1, S, S)
    loss = F.mse_loss(out[:, 0].float(), targets / output_scale_kpa)
    optimizer.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
    else:
        loss.backward()
        optimizer.step()
    return loss.detach()


# --- distributed --------------------------------------------------------------------
@dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1
    owned: bool = False  # we initialised the process group (and destroy it)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def start(cls, device: torch.device) -> _Dist:
        env_world = int(os.environ.get("WORLD_SIZE", "1"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
        if torch_dist.is_available() and torch_dist.is_initialized():
            return cls(torch_dist.get_rank(), torch_dist.get_world_size(), local_rank, local_world)
        if env_world <= 1:
            return cls()
        backend = "nccl" if device.type == "cuda" else "gloo"
        torch_dist.init_process_group(backend=backend)
        return cls(torch_dist.get_rank(), env_world, local_rank, local_world, owned=True)

    def barrier(self) -> None:
        if self.world > 1:
            torch_dist.barrier()

    def all_reduce(self, tensor: torch.Tensor) -> torch.Tensor:
        if self.world > 1:
            torch_dist.all_reduce(tensor)
        return tensor

    def close(self) -> None:
        if self.owned and torch_dist.is_initialized():
            torch_dist.destroy_process_group()


def _resolve_device(config: TrainConfig) -> torch.device:
    """The device by :func:`beadsight.torch_device.resolve_device`; a plain ``cuda`` under
    torchrun is the process's ``LOCAL_RANK`` GPU."""
    device = resolve_device(config.device, "device")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if device.type == "cuda":
        if device.index is None:
            device = torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', '0')) if world > 1 else 0}")
        torch.cuda.set_device(device)
        return device
    if config.precision == "fp16":
        raise ConfigError(f"precision fp16 needs a CUDA device; use bf16 or fp32 on {device}")
    if device.type == "mps" and world > 1:
        raise ConfigError("device mps: one process only (distributed training needs cuda or cpu)")
    return device


# --- the run folder -----------------------------------------------------------------
class RunFolder:
    """Paths and writers of a run folder (only rank 0 writes)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @property
    def last(self) -> Path:
        return self.path / LAST_CHECKPOINT

    @property
    def best(self) -> Path:
        return self.path / BEST_CHECKPOINT

    def write_json(self, name: str, obj: Any) -> None:
        tmp = self.path / f".{name}.tmp"
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n")
        os.replace(tmp, self.path / name)

    def log(self, **values: Any) -> dict[str, Any]:
        line = {key: values.get(key) for key in METRIC_KEYS}
        with (self.path / METRICS_FILE).open("a") as f:
            f.write(json.dumps(line) + "\n")
        return line

    def truncate_metrics(self, step: int) -> None:
        """Drop events after ``step`` (written after the checkpoint a resume starts from)."""
        path = self.path / METRICS_FILE
        if not path.is_file():
            return
        kept = []
        for text in path.read_text().splitlines():
            try:
                line = json.loads(text)
            except json.JSONDecodeError:  # a line cut short by a kill
                continue
            if isinstance(line, dict) and (line.get("step") or 0) <= step:
                kept.append(json.dumps(line))
        tmp = path.with_name(f".{METRICS_FILE}.tmp")
        tmp.write_text("".join(k + "\n" for k in kept))
        os.replace(tmp, path)


# --- data ---------------------------------------------------------------------------
@dataclass
class _Data:
    split: dict[str, np.ndarray]
    labels: dict[str, WindowLabels]
    image_size: int
    fingerprint: str
    frame_mask: np.ndarray  # (N,) frames of the train and val windows


def _check_image_size(config: TrainConfig, ds: Dataset) -> int:
    size = config.image_size or ds.image_size
    if size > ds.image_size:
        raise ConfigError(
            f"image_size {size} is larger than the dataset's {ds.image_size} px frames "
            f"({ds.path}); train at the dataset's size or smaller"
        )
    if size % SIZE_MULTIPLE:
        raise ConfigError(
            f"image_size {size} (of {ds.path}) is not a multiple of {SIZE_MULTIPLE}; "
            f"pass --image-size with a multiple of {SIZE_MULTIPLE}"
        )
    return size


def _prepare_data(
    config: TrainConfig, ds: Dataset, split: dict[str, np.ndarray], image_size: int, fp: str
) -> _Data:
    if len(split["train"]) == 0:
        raise ConfigError(
            f"split {config.split} leaves the train split with no presses "
            f"({ds.num_presses} presses in {ds.path})"
        )
    labels, span = {}, config.span
    for name in ("train", "val"):
        ends = window_ends(ds.press_id, ds.valid, span, presses=split[name])
        labels[name] = WindowLabels.from_dataset(ds, ends, image_size)
    if len(labels["train"]) == 0:
        raise ConfigError(
            f"frames {config.frames} (frame stride {config.frame_stride}): no training window "
            f"fits in the {len(split['train'])} train presses of {ds.path} (each needs {span} "
            "consecutive valid frames)"
        )
    if len(labels["val"]) == 0:
        logger.warning("no validation windows: best.pt will follow the training loss")
    mask = window_frame_mask(np.concatenate([labels[n].ends for n in labels]), span, len(ds))
    return _Data(split, labels, image_size, fp, mask)


def _split_record(config: TrainConfig, ds: Dataset, data: _Data) -> dict[str, Any]:
    return {
        "dataset": str(Path(config.data).resolve()),
        "dataset_fingerprint": data.fingerprint,
        "num_presses": int(ds.num_presses),
        "fractions": list(config.split),
        "seed": config.seed,
        "frames": config.frames,
        "frame_stride": config.frame_stride,
        **{name: [int(i) for i in data.split[name]] for name in SPLITS},
        "windows": {name: len(data.labels[name]) for name in data.labels},
    }


# --- the trainer --------------------------------------------------------------------
class _Trainer:
    def __init__(self, config: TrainConfig, dist: _Dist, device: torch.device):
        self.config, self.dist, self.device = config, dist, device
        self.run = RunFolder(config.out)
        self.step = 0
        self.elapsed_s = 0.0
        self.best: dict[str, Any] = {}
        self.resume_state: dict[str, Any] | None = None

    def _info(self, *args: Any) -> None:
        if self.dist.is_main:
            logger.info(*args)

    # --- setup ---
    def setup(self) -> None:
        config = self.config
        if config.threads:
            torch.set_num_threads(config.threads)
        self._check_run_folder()
        self.ds = open_dataset(config.data)
        self.ds.require_presses()
        image_size = _check_image_size(config, self.ds)
        fingerprint = dataset_fingerprint(self.ds)
        if config.resume:
            model, split = self._load_resume(image_size, fingerprint)
        else:
            split = split_presses(self.ds.num_presses, config.split, config.seed)
            model = None
        self.data = _prepare_data(config, self.ds, split, image_size, fingerprint)
        self.model = model or self._new_model()
        self.module = self.model.module.to(self.device).train()
        self.scale = float(self.model.meta.output_scale_kpa)
        self._make_optimizer()
        self._make_loaders()
        self._write_run_files()

    def _check_run_folder(self) -> None:
        if self.config.resume and not self.run.last.is_file():
            raise CheckpointError(
                f"{self.run.last}: no checkpoint to resume from (out={self.config.out}); "
                "start without --resume"
            )
        if not self.config.resume and self.run.last.is_file():
            raise ConfigError(
                f"out {self.config.out} already holds a training run ({LAST_CHECKPOINT}); pass "
                "--resume to continue it, or choose another --out"
            )

    def _new_model(self) -> PressureModel:
        if self.config.init:
            return self._init_model()
        config, data = self.config, self.data
        geometry = self.ds.geometry.with_image_size(data.image_size)
        train_labels = data.labels["train"]
        mean, std = pixel_stats(
            self.ds,
            window_frame_mask(train_labels.ends, config.span, len(self.ds)),
            data.image_size,
        )
        if not train_labels.contact.any():
            raise DatasetError(
                f"{self.ds.path}: no training window ends in contact, so there is nothing to "
                "learn (and no mean contact force for the output scale)"
            )
        scale = output_scale_kpa(train_labels.force_n[train_labels.contact], geometry)
        meta = CheckpointMeta(
            model=config.model_config(),
            geometry=geometry,
            pixel_mean=mean,
            pixel_std=std,
            channel_order="RGB",
            output_scale_kpa=scale,
            provenance=self._provenance(),
        )
        torch.manual_seed(config.seed)  # identical initial weights on every rank
        model = PressureModel.create(meta)
        self._info(
            "normalisation: pixel mean %s std %s (RGB), output scale %.4f kPa",
            np.round(mean, 2).tolist(),
            np.round(std, 2).tolist(),
            scale,
        )
        return model

    def _provenance(self) -> dict[str, Any]:
        provenance = {
            "source": "beadsight train",
            "beadsight_version": __version__,
            "dataset": str(Path(self.config.data).resolve()),
            "dataset_source": self.ds.provenance.get("source"),
            "fps": float(self.ds.fps),  # camera rate: the predictor's gap detection uses it
            "created_unix": time.time(),
        }
        sim = self.ds.provenance.get("simulator")
        if isinstance(sim, dict):  # simulated data: the demo keeps its held-out presses apart
            provenance["sim"] = {"seed": sim.get("seed"), "config": sim.get("config")}
        return provenance

    def _init_model(self) -> PressureModel:
        """The ``init`` checkpoint's weights and normalisation, with this run's dropout."""
        config, path = self.config, self.config.init
        source = load_checkpoint(path)
        wanted = config.model_config()
        for name in INIT_SHAPE_FIELDS:
            have, want = getattr(source.meta.model, name), getattr(wanted, name)
            if have != want:
                raise ConfigError(
                    f"init {path}: {name} is {have} in the checkpoint but {want} in this run; "
                    f"leave --{name.replace('_', '-')} out to take the checkpoint's"
                )
        meta = dataclasses.replace(
            source.meta,
            model=wanted,
            geometry=self.ds.geometry.with_image_size(self.data.image_size),
            provenance={
                **self._provenance(),
                "init": {"path": str(Path(path).resolve()), "provenance": source.meta.provenance},
            },
            training={},
        )
        model = PressureModel.create(meta)
        model.module.net.load_state_dict(source.module.net.state_dict())
        self._info("initialised from %s (keeping its normalisation and output scale)", path)
        if source.image_size != self.data.image_size:
            # the U-Net is fully convolutional and pressure is per area: the weights carry
            # over to another resolution and go on learning there
            self._info(
                "the checkpoint was trained at %d px; this run trains it at %d px",
                source.image_size,
                self.data.image_size,
            )
        return model

    def _load_resume(self, image_size: int, fingerprint: str) -> tuple[PressureModel, dict]:
        path = self.run.last
        state = read_checkpoint_file(path)
        model = load_checkpoint(path)
        training = model.meta.training
        stored_fp = training.get("dataset_fingerprint")
        if stored_fp != fingerprint:
            raise CheckpointError(
                f"{path}: dataset_fingerprint {stored_fp} of the run does not match {fingerprint} "
                f"of {self.config.data}; resume with the dataset the run was trained on"
            )
        stored = dict(training.get("config", {}))
        stored["image_size"] = model.image_size
        current = {**self.config.to_dict(), "image_size": image_size}
        fixed = RESUME_FIXED_FIELDS
        if current["lr_schedule"] != "constant":  # the schedule spans the run's length
            fixed = (*fixed, "steps", "epochs")
        for name in fixed:
            a, b = stored.get(name, TrainConfig.__dataclass_fields__[name].default), current[name]
            if (list(a) if isinstance(a, (list, tuple)) else a) != (
                list(b) if isinstance(b, (list, tuple)) else b
            ):
                raise CheckpointError(
                    f"{path}: field '{name}' is {a!r} in the checkpoint but {b!r} in this "
                    "configuration; a resumed run keeps its settings (start a new --out to change it)"
                )
        split = {name: np.asarray(training["split"][name], dtype=np.int64) for name in SPLITS}
        self.resume_state = state
        self.step = int(state.get("step", training.get("step", 0)))
        self.elapsed_s = float(state.get("elapsed_s", 0.0))
        self.best = dict(training.get("best_val") or {})
        return model, split

    def _make_optimizer(self) -> None:
        config = self.config
        net = self.module.net
        self.optimizer = torch.optim.AdamW(
            net.parameters(), lr=config.lr, weight_decay=config.weight_decay
        )
        self.scaler = torch.amp.GradScaler("cuda") if config.precision == "fp16" else None
        self.autocast_dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(config.precision)
        if self.resume_state is not None:
            self.optimizer.load_state_dict(self.resume_state["optimizer"])
            if self.scaler is not None and self.resume_state.get("scaler"):
                self.scaler.load_state_dict(self.resume_state["scaler"])
            self._restore_rng(self.resume_state)
        else:
            torch.manual_seed(config.seed + self.dist.rank)  # noise/dropout differ by rank
        self.ddp = net
        if self.dist.world > 1:
            self.ddp = torch.nn.parallel.DistributedDataParallel(
                net, device_ids=[self.device.index] if self.device.type == "cuda" else None
            )

    def _restore_rng(self, state: dict) -> None:
        rng = state.get("rng_cpu")
        if isinstance(rng, list) and len(rng) > self.dist.rank:
            torch.set_rng_state(rng[self.dist.rank])
        cuda = state.get("rng_cuda")
        if self.device.type == "cuda" and isinstance(cuda, list) and len(cuda) > self.dist.rank:
            torch.cuda.set_rng_state(cuda[self.dist.rank], self.device)

    def _make_loaders(self) -> None:
        config, data, dist = self.config, self.data, self.dist
        if config.batch_size % dist.world:
            raise ConfigError(
                f"batch_size {config.batch_size} is not divisible by the {dist.world} processes"
            )
        per_rank, span = config.batch_size // dist.world, config.span
        copies = dist.local_world if self.device.type == "cpu" else 1
        mode = choose_loader_mode(
            config.loader,
            DeviceFrames.nbytes(data.frame_mask, data.image_size),
            self.device,
            copies,
        )
        if mode == "device":
            store = DeviceFrames.load(
                self.ds,
                data.frame_mask,
                data.image_size,
                self.device,
                progress=config.progress and dist.is_main,
            )
            sources = {name: DeviceWindows(store, data.labels[name], span) for name in data.labels}
        else:
            sources = {
                name: WindowDataset(config.data, data.labels[name], span) for name in data.labels
            }
        common = dict(
            device=self.device,
            seed=config.seed,
            rank=dist.rank,
            world_size=dist.world,
            num_workers=config.num_workers,
        )
        self.train_loader = WindowLoader(
            sources["train"], per_rank, shuffle=True, augment=True, **common
        )
        self.val_loader = WindowLoader(
            sources["val"],
            per_rank,
            shuffle=False,
            augment=False,
            stride=config.val_stride,
            pad=False,
            **common,
        )
        self.loader_mode = mode
        self.steps_per_epoch = batches_per_epoch(len(data.labels["train"]), per_rank, dist.world)
        self._info(
            "%d train windows (%d steps/epoch), %d val windows, %d px, %s loader, device %s, %s",
            len(data.labels["train"]),
            self.steps_per_epoch,
            self.val_loader.num_windows,
            data.image_size,
            mode,
            self.device,
            config.precision,
        )

    def _write_run_files(self) -> None:
        if self.dist.is_main:
            self.run.path.mkdir(parents=True, exist_ok=True)
            resolved = {
                **self.config.to_dict(),
                "data": str(Path(self.config.data).resolve()),
                "out": str(self.run.path.resolve()),
            }
            self.run.write_json(CONFIG_FILE, resolved)
            self.run.write_json(SPLIT_FILE, _split_record(self.config, self.ds, self.data))
            if self.config.resume:
                self.run.truncate_metrics(self.step)
                logger.info("resuming %s at step %d", self.run.path, self.step)
        self.dist.barrier()

    # --- checkpoints ---
    def _training_meta(self) -> dict[str, Any]:
        data = self.data
        return {
            "dataset_path": str(Path(self.config.data).resolve()),
            "dataset_fingerprint": data.fingerprint,
            "split": {
                **{name: [int(i) for i in data.split[name]] for name in SPLITS},
                "num_presses": int(self.ds.num_presses),
            },
            "split_fractions": list(self.config.split),
            "split_seed": self.config.seed,
            "windows": {name: len(data.labels[name]) for name in data.labels},
            "config": self.config.to_dict(),
            "step": self.step,
            "epoch": self.step // self.steps_per_epoch,
            "steps_per_epoch": self.steps_per_epoch,
            "world_size": self.dist.world,
            "best_val": self.best,
        }

    def _rng_states(self) -> dict[str, Any]:
        """Every rank's RNG states (gathered to rank 0)."""
        cpu = torch.get_rng_state()
        cuda = torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else None
        if self.dist.world == 1:
            return {"rng_cpu": [cpu], "rng_cuda": [cuda] if cuda is not None else None}
        cpus: list[Any] = [None] * self.dist.world
        cudas: list[Any] = [None] * self.dist.world
        torch_dist.all_gather_object(cpus, cpu)
        torch_dist.all_gather_object(cudas, cuda)
        return {"rng_cpu": cpus, "rng_cuda": cudas if cuda is not None else None}

    def save(self, best: bool = False) -> None:
        """Write last.pt (full training state) and, if ``best``, best.pt; all ranks call it."""
        rng = self._rng_states()
        if self.dist.is_main:
            self.model.meta.training = self._training_meta()
            self.model.save(
                self.run.last,
                optimizer=self.optimizer.state_dict(),
                scaler=self.scaler.state_dict() if self.scaler is not None else None,
                step=self.step,
                epoch=self.step // self.steps_per_epoch,
                steps_per_epoch=self.steps_per_epoch,
                elapsed_s=self._elapsed(),
                best_val=self.best,
                **rng,
            )
            if best:
                self.model.save(self.run.best, step=self.step)
        self.dist.barrier()
        self._last_save = time.monotonic()

    # --- steps ---
    def _autocast(self):
        return autocast(self.device, self.autocast_dtype)

    def train_step(self, frames: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        return optimizer_step(
            self.module,
            self.ddp,
            self.optimizer,
            frames,
            targets,
            output_scale_kpa=self.scale,
            noise_std=self.config.noise_std,
            autocast_dtype=self.autocast_dtype,
            scaler=self.scaler,
        )

    @torch.no_grad()
    def validate(self) -> dict[str, float] | None:
        """Mean squared error of the normalised map and MAE in kPa over the val windows."""
        self.module.eval()
        sums = torch.zeros(3, dtype=torch.float64, device=self.device)
        self.val_loader.set_epoch(0)
        bar = tqdm(
            self.val_loader,
            desc="validating",
            leave=False,
            mininterval=1.0,
            disable=not (self.config.progress and self.dist.is_main),
        )
        for frames, targets in bar:
            x = model_inputs(self.module, frames)  # no noise
            with self._autocast():
                out = self.module.net(x)[:, 0].float()
            sums[0] += ((out - targets / self.scale) ** 2).sum(dtype=torch.float64)
            sums[1] += (out * self.scale - targets).abs().sum(dtype=torch.float64)
            sums[2] += targets.numel()
        self.module.train()
        sums = self.dist.all_reduce(sums).tolist()
        if sums[2] == 0:
            return None
        return {"val_loss": sums[0] / sums[2], "val_mae_kpa": sums[1] / sums[2]}

    # --- the loop ---
    def _elapsed(self) -> float:
        return self.elapsed_s + time.monotonic() - self._t0

    def _log(self, **values: Any) -> None:
        if self.dist.is_main:
            line = self.run.log(
                step=self.step,
                epoch=round(self.step / self.steps_per_epoch, 4),
                lr=self.optimizer.param_groups[0]["lr"],
                time_s=round(self._elapsed(), 3),
                wall_time=round(time.time(), 3),
                **values,
            )
            logger.debug("metrics %s", line)

    def _flush_interval(self) -> tuple[float | None, bool]:
        """Log the mean training loss since the last log (over all ranks); returns it and
        whether a timed checkpoint is due (agreed by all ranks)."""
        iv = self._interval
        due = time.monotonic() - self._last_save >= 60 * self.config.checkpoint_every_min
        if iv["steps"] == 0:
            return None, due
        packed = torch.stack(
            [
                iv["loss_sum"].double(),
                torch.tensor(float(due), device=self.device, dtype=torch.float64),
            ]
        )
        packed = self.dist.all_reduce(packed).tolist()
        loss = packed[0] / (iv["steps"] * self.dist.world)
        if not math.isfinite(loss):
            raise BeadSightError(
                f"training diverged: loss {loss} at step {self.step}; the last good checkpoint is "
                f"{self.run.last} (try a lower lr, or precision fp32)"
            )
        seconds = time.monotonic() - iv["t0"]
        samples = iv["steps"] * self.config.batch_size
        self._log(event="train", train_loss=loss, samples_per_s=samples / max(seconds, 1e-9))
        self._epoch_loss[0] += loss * iv["steps"]
        self._epoch_loss[1] += iv["steps"]
        self._interval = {
            "loss_sum": torch.zeros((), device=self.device),
            "steps": 0,
            "t0": time.monotonic(),
        }
        return loss, packed[1] > 0

    def _after_step(self, bar: tqdm) -> None:
        config, single = self.config, self.dist.world == 1
        now = time.monotonic()
        log_due = self.step % config.log_every_steps == 0 or (
            single and now - self._interval["t0"] >= MAX_LOG_INTERVAL_S
        )
        timed_save = False
        if log_due:
            loss, timed_save = self._flush_interval()
            if loss is not None:
                bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
        elif single:  # no collective needed to agree on the clock
            timed_save = now - self._last_save >= 60 * config.checkpoint_every_min
        if timed_save or self.step % config.checkpoint_every_steps == 0:
            self.save()

    def _end_of_epoch(self) -> None:
        self._flush_interval()
        total, n = self._epoch_loss
        train_loss = total / n if n else None
        self._epoch_loss = [0.0, 0]
        metrics = self.validate()
        key = "val_loss" if metrics else "train_loss"
        value = metrics["val_loss"] if metrics else train_loss
        improved = value is not None and value < self.best.get(key, math.inf)
        if improved:
            self.best = {
                key: value,
                **(metrics or {}),
                "step": self.step,
                "epoch": self.step // self.steps_per_epoch,
            }
        self._log(event="val", train_loss=train_loss, **(metrics or {}))
        if metrics and self.dist.is_main:
            logger.info(
                "step %d: val loss %.5f, val MAE %.4f kPa%s",
                self.step,
                metrics["val_loss"],
                metrics["val_mae_kpa"],
                " (best)" if improved else "",
            )
        self.save(best=improved or not self.run.best.is_file())

    def loop(self) -> None:
        config, spe = self.config, self.steps_per_epoch
        total = config.steps if config.steps is not None else config.epochs * spe
        self._t0 = self._last_save = time.monotonic()
        self._interval = {
            "loss_sum": torch.zeros((), device=self.device),
            "steps": 0,
            "t0": time.monotonic(),
        }
        self._epoch_loss = [0.0, 0]
        if self.step >= total:
            logger.info("run %s already reached step %d of %d", self.run.path, self.step, total)
            return
        bar = tqdm(
            total=total,
            initial=self.step,
            desc="training",
            unit="step",
            mininterval=1.0,
            disable=not (config.progress and self.dist.is_main),
        )
        try:
            while self.step < total:
                epoch, skip = divmod(self.step, spe)
                self.train_loader.set_epoch(epoch, skip)
                start = self.step
                for frames, targets in self.train_loader:
                    for group in self.optimizer.param_groups:
                        group["lr"] = config.learning_rate(self.step, total)
                    self._interval["loss_sum"] += self.train_step(frames, targets)
                    self._interval["steps"] += 1
                    self.step += 1
                    bar.update(1)
                    if self.step % spe == 0 or self.step >= total:
                        break  # the epoch's end saves
                    self._after_step(bar)
                if self.step == start:
                    raise RuntimeError(f"epoch {epoch} yielded no training batch (skip {skip})")
                self._end_of_epoch()
        except KeyboardInterrupt:
            if self.dist.world == 1:
                logger.warning("interrupted at step %d: saving %s", self.step, self.run.last)
                self.save()
            raise
        finally:
            bar.close()

    def close(self) -> None:
        for loader in (getattr(self, "train_loader", None), getattr(self, "val_loader", None)):
            if loader is not None and isinstance(loader.source, WindowDataset):
                loader.source.close()
        if getattr(self, "ds", None) is not None:
            self.ds.close()


def train(config: TrainConfig) -> Path:
    """Train a pressure model as ``config`` says; returns the run folder.

    Under ``torchrun`` every process calls this; it joins (or starts) the process
    group, and only rank 0 writes files.
    """
    device = _resolve_device(config)
    dist = _Dist.start(device)
    trainer = _Trainer(config, dist, device)
    try:
        trainer.setup()
        trainer.loop()
    finally:
        trainer.close()
        dist.close()
    return Path(config.out)
