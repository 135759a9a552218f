"""What a training run starts from: the windows of its split, and its model - new
(normalisation measured on the training split), fine-tuned from an ``init``
checkpoint, or resumed from the run's own ``last.pt``.

Normalisation of a new model is measured on the training split at the training image
size: ``pixel_mean``/``pixel_std`` per RGB channel in 0..255 units, and
``output_scale_kpa`` as the reference's ``avg_pressure``: the pressure of the finger
disk carrying the mean in-contact force, averaged over the whole image, i.e.
``disk_pressure(F_mean) * disk_pixels / S^2`` (see :func:`output_scale_kpa`).
A fine-tuned model keeps its checkpoint's normalisation and output scale, which its
weights were trained for.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from beadsight import __version__
from beadsight.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    PressureModel,
    load_checkpoint,
    read_checkpoint_file,
)
from beadsight.config import ConfigError, SensorGeometry
from beadsight.data.dataset import Dataset, DatasetError
from beadsight.data.splits import SPLITS, dataset_window_ends, split_presses
from beadsight.data.windows import pixel_stats
from beadsight.geometry import disk_maps
from beadsight.train.config import (
    INIT_SHAPE_FIELDS,
    RESUME_FIXED_FIELDS,
    SIZE_MULTIPLE,
    TRAIN_LAYERS,
    TrainConfig,
    field_default,
)
from beadsight.train.windows import WindowLabels

logger = logging.getLogger(__name__)

DECODER_LAYERS = ("U2", "C7", "U3", "C8", "U4", "C9", "pred")  # model.UNet's up path and head


# --- data ---------------------------------------------------------------------------
@dataclass
class RunData:
    """The run's split and the labels of its train and val windows."""

    split: dict[str, np.ndarray]  # press ids per split
    labels: dict[str, WindowLabels]  # "train", "val"
    image_size: int  # px the run trains at
    fingerprint: str  # of the dataset (dataset_fingerprint)
    frame_mask: np.ndarray  # (N,) frames of the train and val windows


def check_image_size(config: TrainConfig, ds: Dataset) -> int:
    """The image size the run trains at: ``config.image_size`` or the dataset's."""
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


def prepare_data(
    config: TrainConfig, ds: Dataset, split: dict[str, np.ndarray], image_size: int, fp: str
) -> RunData:
    """The train and val windows of ``split`` (ids of presses per split)."""
    if len(split["train"]) == 0:
        raise ConfigError(
            f"split {config.split} leaves the train split with no presses "
            f"({ds.num_presses} presses in {ds.path})"
        )
    labels, span, rest = {}, config.span, config.rest_input
    for name in ("train", "val"):
        ends = dataset_window_ends(ds, span, presses=split[name], rest=rest)
        labels[name] = WindowLabels.from_dataset(ds, ends, image_size, rest=rest)
    if len(labels["train"]) == 0:
        raise ConfigError(
            f"frames {config.frames} (frame stride {config.frame_stride}): no frame of the "
            f"{len(split['train'])} train presses of {ds.path} has the {span} consecutive valid "
            "frames of history a training window needs"
        )
    if len(labels["val"]) == 0:
        logger.warning("no validation windows: best.pt will follow the training loss")
    mask = labels["train"].frame_mask(span, len(ds)) | labels["val"].frame_mask(span, len(ds))
    return RunData(split, labels, image_size, fp, mask)


def split_used_presses(config: TrainConfig, ds: Dataset) -> dict[str, np.ndarray]:
    """The run's split: the presses it uses (``presses`` of them after the first
    ``skip_presses``) shuffled with ``seed`` and cut by ``split``; dataset press ids."""
    first = config.skip_presses
    stop = ds.num_presses if config.presses is None else min(first + config.presses, ds.num_presses)
    if stop <= first:
        raise ConfigError(
            f"skip_presses {first} leaves no press of the {ds.num_presses} in {ds.path}"
        )
    split = split_presses(stop - first, config.split, config.seed)
    return {name: ids + first for name, ids in split.items()}


def trainable_parameters(net: torch.nn.Module, layers: str) -> list[torch.nn.Parameter]:
    """The parameters ``layers`` ("all", or "decoder": the up path and the head) trains;
    the others get ``requires_grad=False``."""
    if layers not in TRAIN_LAYERS:
        raise ConfigError(f"train_layers must be one of {TRAIN_LAYERS}, got {layers!r}")
    chosen = []
    for name, param in net.named_parameters():
        if not param.is_floating_point():  # a quantizer's settings (--qat)
            continue
        train = layers == "all" or name.split(".")[0] in DECODER_LAYERS
        param.requires_grad_(train)
        if train:
            chosen.append(param)
    return chosen


def split_record(config: TrainConfig, ds: Dataset, data: RunData) -> dict[str, Any]:
    """The run folder's split.json."""
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


# --- a new model --------------------------------------------------------------------
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


def run_relative(path: str | Path, config: TrainConfig) -> str:
    """``path`` as the run folder ``config.out`` reaches it (``../data/train.h5``): what a
    checkpoint records, so that its model card names no folder of the training machine."""
    return os.path.relpath(Path(path).resolve(), Path(config.out).resolve())


def provenance(config: TrainConfig, ds: Dataset) -> dict[str, Any]:
    """Where a trained model comes from (stored in its checkpoints); paths as
    :func:`run_relative` names them."""
    record = {
        "source": "beadsight train",
        "beadsight_version": __version__,
        "dataset": run_relative(config.data, config),
        "dataset_source": ds.provenance.get("source"),
        "fps": float(ds.fps),  # camera rate: the predictor's gap detection uses it
        "created_unix": time.time(),
    }
    sim = ds.provenance.get("simulator")
    if isinstance(sim, dict):  # simulated data: the demo keeps its held-out presses apart
        record["sim"] = {"seed": sim.get("seed"), "config": sim.get("config")}
    return record


def new_model(
    config: TrainConfig, ds: Dataset, data: RunData, info: Callable[..., None] = logger.info
) -> PressureModel:
    """A model with fresh weights (seeded alike on every rank) and the normalisation of
    the training split. ``info``: where to log it (the trainer logs on rank 0 only)."""
    geometry = ds.geometry.with_image_size(data.image_size)
    train_labels = data.labels["train"]
    mask = train_labels.frame_mask(config.span, len(ds))
    mean, std = pixel_stats(ds, mask, data.image_size)
    if not train_labels.contact.any():
        raise DatasetError(
            f"{ds.path}: no training window ends in contact, so there is nothing to "
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
        provenance=provenance(config, ds),
    )
    torch.manual_seed(config.seed)  # identical initial weights on every rank
    model = PressureModel.create(meta)
    info(
        "normalisation: pixel mean %s std %s (RGB), output scale %.4f kPa",
        np.round(mean, 2).tolist(),
        np.round(std, 2).tolist(),
        scale,
    )
    return model


def init_model(
    config: TrainConfig, ds: Dataset, data: RunData, info: Callable[..., None] = logger.info
) -> PressureModel:
    """The ``init`` checkpoint's weights and normalisation, with this run's dropout."""
    path = config.init
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
        geometry=ds.geometry.with_image_size(data.image_size),
        provenance={
            **provenance(config, ds),
            "init": {"path": run_relative(path, config), "provenance": source.meta.provenance},
        },
        training={},
    )
    model = PressureModel.create(meta)
    model.module.net.load_state_dict(source.module.net.state_dict())
    info("initialised from %s (keeping its normalisation and output scale)", path)
    if source.image_size != data.image_size:
        # the U-Net is fully convolutional and pressure is per area: the weights carry
        # over to another resolution and go on learning there
        info(
            "the checkpoint was trained at %d px; this run trains it at %d px",
            source.image_size,
            data.image_size,
        )
    return model


# --- resuming -----------------------------------------------------------------------
@dataclass
class Resumed:
    """What ``last.pt`` holds to continue a run."""

    model: PressureModel
    split: dict[str, np.ndarray]
    state: dict[str, Any]  # the file's training state (optimizer, scaler, RNG, step, ...)
    step: int
    elapsed_s: float
    best: dict[str, Any] = field(default_factory=dict)


def load_resume(path: Path, config: TrainConfig, image_size: int, fingerprint: str) -> Resumed:
    """Read ``path`` (a run's last.pt) and check that ``config`` continues that run."""
    state = read_checkpoint_file(path)
    model = load_checkpoint(path)
    training = model.meta.training
    stored_fp = training.get("dataset_fingerprint")
    if stored_fp != fingerprint:
        raise CheckpointError(
            f"{path}: dataset_fingerprint {stored_fp} of the run does not match {fingerprint} "
            f"of {config.data}; resume with the dataset the run was trained on"
        )
    stored = {**training.get("config", {}), "image_size": model.image_size}
    current = {**config.to_dict(), "image_size": image_size}
    fixed = RESUME_FIXED_FIELDS
    if current["lr_schedule"] != "constant":  # the schedule spans the run's length
        fixed = (*fixed, "steps", "epochs")
    for name in fixed:
        a, b = stored.get(name, field_default(name)), current[name]
        if _plain(a) != _plain(b):
            raise CheckpointError(
                f"{path}: field '{name}' is {a!r} in the checkpoint but {b!r} in this "
                "configuration; a resumed run keeps its settings (start a new --out to change it)"
            )
    with tampered_state_errors(path):
        split = {name: np.asarray(training["split"][name], dtype=np.int64) for name in SPLITS}
        return Resumed(
            model=model,
            split=split,
            state=state,
            step=int(state.get("step", training.get("step", 0))),
            elapsed_s=float(state.get("elapsed_s", 0.0)),
            best=dict(training.get("best_val") or {}),
        )


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: Any) -> None:
    """``optimizer.load_state_dict(state)``; ValueError unless every tensor of the loaded
    state (Adam's moments) has its parameter's shape: a state of another model would fail
    only at the next step."""
    optimizer.load_state_dict(state)
    for group in optimizer.param_groups:
        for param in group["params"]:
            for name, value in optimizer.state.get(param, {}).items():
                if torch.is_tensor(value) and value.ndim and value.shape != param.shape:
                    raise ValueError(
                        f"optimizer state {name!r} has shape {tuple(value.shape)}, expected "
                        f"{tuple(param.shape)}"
                    )


@contextmanager
def tampered_state_errors(path: Path) -> Iterator[None]:
    """Any error reading or applying ``path``'s training state (a damaged or tampered
    last.pt: missing keys, wrong types, optimizer or RNG states of another shape) becomes
    one CheckpointError naming the file."""
    try:
        yield
    except (KeyError, TypeError, ValueError, IndexError, RuntimeError, AttributeError) as e:
        if isinstance(e, CheckpointError):
            raise
        raise CheckpointError(
            f"{path}: the training state cannot be resumed ({type(e).__name__}: "
            f"{str(e).splitlines()[0] if str(e) else 'malformed'}); the file is damaged or "
            "was not written by this run: start a new --out"
        ) from None


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, (list, tuple)) else value
