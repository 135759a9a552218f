"""The training commands: ``beadsight train --data D --out RUN [...]`` and
``beadsight average A.pt B.pt --out C.pt``."""

from __future__ import annotations

import argparse
import os

from beadsight.cli.options import MINUTES

# TrainConfig fields offered as flags. Their defaults stay None ("not given") so that
# only flags the user gives override the TOML file / the resumed run's config; the
# help shows TrainConfig's default.
TRAIN_FLAGS = (
    ("steps", "optimizer steps in total (default: --epochs passes)", {"type": int}),
    ("epochs", "passes over the training windows"),
    (
        "budget_min",
        "wall-clock budget in minutes: stop then (or at --steps/--epochs, whichever is first)",
        {"type": MINUTES, "metavar": "M"},
    ),
    (
        "val_every_min",
        "also validate this often, minutes (default: every epoch)",
        {"type": MINUTES},
    ),
    ("presses", "train on only this many presses of the dataset", {"type": int}),
    ("skip_presses", "drop the dataset's first presses (a new pouch's break-in)"),
    ("train_layers", "all, or decoder (the encoder stays as initialised)"),
    ("augment", "no dihedral augmentation"),
    (
        "rest_input",
        "rest-referenced model: it also sees an image of the unloaded pouch (pressure is "
        "the change from rest, so a steady load keeps its reading)",
    ),
    (
        "rest_norm",
        "with --rest-input: the network sees the rest image standardised per channel and each "
        "frame's change from rest divided by the rest's contrast, so a pouch's colours and "
        "contrast matter less (for models meant for pouches of other looks)",
    ),
    (
        "color_jitter",
        "random colour, contrast and brightness changes of each training input, 0..1 "
        "(for models meant for pouches of other looks)",
        {"type": float},
    ),
    (
        "qat",
        "quantization-aware training: train through int8 quantizers so that the int8 "
        "runtime keeps the paper's metrics (for reference-size models on a CPU; a "
        "fine-tune with --init; needs nncf)",
    ),
    ("batch_size", "windows per step over all processes"),
    ("lr", "AdamW learning rate"),
    ("lr_schedule", "constant, or cosine: decay from --lr to --lr-min over the run's steps"),
    ("lr_min", "final learning rate of the cosine schedule"),
    (
        "init",
        "start from this checkpoint's weights and normalisation (fine-tuning); frames, "
        "frame stride, width and up-kernel default to the checkpoint's",
        {"metavar": "CHECKPOINT"},
    ),
    ("weight_decay", "AdamW weight decay"),
    ("dropout", "dropout in the U-Net conv blocks"),
    ("width", "U-Net width (channels of the first block)"),
    ("frames", "T: frames the network sees per prediction"),
    ("frame_stride", "those frames are this many camera frames apart (1: consecutive)"),
    ("up_kernel", "U-Net up-conv kernel, 1 (reference) or 3", {"choices": (1, 3)}),
    (
        "image_size",
        "train at this size in px, a multiple of 8; frames are resized with INTER_AREA "
        "(default: the dataset's size)",
        {"type": int},
    ),
    ("device", "auto, cpu, cuda, cuda:N or mps"),
    ("precision", "fp32, bf16 (autocast) or fp16 (CUDA only)"),
    ("seed", "seed of split, init, batch order and augmentation"),
    ("noise_std", "Gaussian noise on the normalised input frames"),
    ("split", "fractions of presses per split", {"nargs": 3, "metavar": ("TRAIN", "VAL", "TEST")}),
    ("loader", "auto, host (DataLoader workers) or device (frames on the device)"),
    ("num_workers", "DataLoader workers in host loader mode"),
    (
        "threads",
        "torch CPU threads (default: on a CPU, the faster of torch's default and 1, timed"
        " on the run's own steps)",
        {"type": int},
    ),
    ("log_every_steps", "a metrics.jsonl line every N steps"),
    ("checkpoint_every_steps", "save last.pt every N steps"),
    ("checkpoint_every_min", "save last.pt at least every M minutes"),
    ("val_stride", "validate on every N-th validation window"),
    ("progress", "no progress bars"),
)


def register(commands) -> None:
    commands.add("train", _train, _arguments)
    commands.add("average", _average, _average_arguments)


def _arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_fields
    from beadsight.train.config import (
        LOADER_MODES,
        LR_SCHEDULES,
        PRECISIONS,
        TRAIN_LAYERS,
        TrainConfig,
    )

    p.add_argument("--data", default=None, help="dataset .h5 (ours or a reference HDF5 file)")
    p.add_argument("--out", default=None, help="run folder to create (or to resume)")
    p.add_argument(
        "--config",
        default=None,
        metavar="FILE.toml",
        help="TOML file of training settings (TrainConfig field names)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        default=None,
        help="continue the run in --out from its last.pt (same split, optimizer, step)",
    )
    choices = {
        "lr_schedule": LR_SCHEDULES,
        "precision": PRECISIONS,
        "loader": LOADER_MODES,
        "train_layers": TRAIN_LAYERS,
    }
    rows = [
        (name, help, {**(extra[0] if extra else {}), **_choices(choices, name)})
        for name, help, *extra in TRAIN_FLAGS
    ]
    add_fields(p, TrainConfig, rows, override=True)


def _choices(choices: dict, name: str) -> dict:
    return {"choices": choices[name]} if name in choices else {}


def _train(args: argparse.Namespace) -> int:
    """Train a pressure model on a dataset.

    Train the BeadSight U-Net (reference recipe by default) into a run folder with
    config.json, split.json, metrics.jsonl, last.pt and best.pt. Settings: code
    defaults < --config FILE.toml < flags. Under torchrun it trains data-parallel.
    """
    from beadsight.cli.options import field_values
    from beadsight.train.config import TrainConfig, resolve_train_config
    from beadsight.train.trainer import train

    overrides = field_values(args, TrainConfig)
    config = resolve_train_config(overrides, args.config)
    run = train(config)
    if os.environ.get("RANK", "0") != "0":  # under torchrun, rank 0 reports
        return 0
    print(f"run folder: {run}")
    print(f"  best checkpoint: {run / 'best.pt'}")
    print(f"  last checkpoint: {run / 'last.pt'}")
    return 0


def _average_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoints", nargs="+", metavar="CKPT", help="checkpoints of one model")
    p.add_argument("--out", required=True, help="checkpoint to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument(
        "--weights",
        type=float,
        nargs="+",
        default=None,
        metavar="W",
        help="relative weight of each checkpoint (default: equal)",
    )


def _average(args: argparse.Namespace) -> int:
    """Average the weights of checkpoints of one model (a model soup).

    The checkpoints must share the network, geometry and normalisation (runs that continue
    one another, or start from one checkpoint); the average can read new presses better
    than each of them, at no cost at run time. Score it with `beadsight evaluate` before
    using it. The output's provenance lists each checkpoint and its weight.
    """
    from beadsight.checkpoint import averaged_from, save_checkpoint
    from beadsight.files import refuse_existing
    from beadsight.train.average import average_checkpoints

    refuse_existing(args.out, args.overwrite)
    model = average_checkpoints(args.checkpoints, args.weights)
    path = save_checkpoint(args.out, model)
    print(f"wrote {path}: the mean of {', '.join(averaged_from(model.meta.provenance))}")
    return 0
