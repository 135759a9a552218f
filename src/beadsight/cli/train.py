"""Training command: ``beadsight train --data D --out RUN [...]``."""

from __future__ import annotations

import argparse
import os

from beadsight.train.trainer import TrainConfig

# CLI flag -> TrainConfig field, with argparse options. Defaults stay None so that
# only flags the user gives override the TOML file / the resumed run's config.
_DEFAULTS = {
    f: TrainConfig.__dataclass_fields__[f].default for f in TrainConfig.__dataclass_fields__
}


def _flag(p: argparse.ArgumentParser, name: str, help: str, **kwargs) -> None:
    default = _DEFAULTS.get(name.replace("-", "_"))
    suffix = "" if default is None else f" (default: {default})"
    p.add_argument(f"--{name}", default=None, help=help + suffix, **kwargs)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a pressure model on a dataset",
        description="Train the BeadSight U-Net (reference recipe by default) into a run folder "
        "with config.json, split.json, metrics.jsonl, last.pt and best.pt. Settings: code "
        "defaults < --config FILE.toml < flags. Under torchrun it trains data-parallel.",
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
    _flag(p, "steps", "optimizer steps in total (default: --epochs passes)", type=int)
    _flag(p, "epochs", "passes over the training windows", type=int)
    _flag(p, "batch-size", "windows per step over all processes", type=int)
    _flag(p, "lr", "AdamW learning rate", type=float)
    _flag(
        p,
        "lr-schedule",
        "constant, or cosine: decay from --lr to --lr-min over the run's steps",
        choices=("constant", "cosine"),
    )
    _flag(p, "lr-min", "final learning rate of the cosine schedule", type=float)
    _flag(
        p,
        "init",
        "start from this checkpoint's weights and normalisation (fine-tuning); frames, "
        "frame stride, width and up-kernel default to the checkpoint's",
        metavar="CHECKPOINT",
    )
    _flag(p, "weight-decay", "AdamW weight decay", type=float)
    _flag(p, "dropout", "dropout in the U-Net conv blocks", type=float)
    _flag(p, "width", "U-Net width (channels of the first block)", type=int)
    _flag(p, "frames", "T: frames the network sees per prediction", type=int)
    p.add_argument("--window", type=int, default=None, help=argparse.SUPPRESS)  # old --frames
    _flag(
        p,
        "frame-stride",
        "those frames are this many camera frames apart (1: consecutive, the reference)",
        type=int,
    )
    _flag(p, "up-kernel", "U-Net up-conv kernel, 1 (reference) or 3", type=int, choices=(1, 3))
    _flag(
        p,
        "image-size",
        "train at this size in px, a multiple of 8; frames are resized with INTER_AREA (default: the dataset's size)",
        type=int,
    )
    _flag(p, "device", "auto, cpu, cuda or cuda:N")
    _flag(
        p,
        "precision",
        "fp32, bf16 (autocast) or fp16 (CUDA only)",
        choices=("fp32", "bf16", "fp16"),
    )
    _flag(p, "seed", "seed of split, init, batch order and augmentation", type=int)
    _flag(p, "noise-std", "Gaussian noise on the normalised input frames", type=float)
    p.add_argument(
        "--split",
        type=float,
        nargs=3,
        default=None,
        metavar=("TRAIN", "VAL", "TEST"),
        help="fractions of presses per split (default: 0.7 0.1 0.2)",
    )
    _flag(
        p,
        "loader",
        "auto, host (DataLoader workers) or device (frames on the device)",
        choices=("auto", "host", "device"),
    )
    _flag(p, "num-workers", "DataLoader workers in host loader mode", type=int)
    _flag(p, "threads", "torch CPU threads (default: torch's choice)", type=int)
    _flag(p, "log-every-steps", "a metrics.jsonl line every N steps", type=int)
    _flag(p, "checkpoint-every-steps", "save last.pt every N steps", type=int)
    _flag(p, "checkpoint-every-min", "save last.pt at least every M minutes", type=float)
    _flag(p, "val-stride", "validate on every N-th validation window", type=int)
    p.add_argument(
        "--no-progress",
        dest="progress",
        action="store_false",
        default=None,
        help="no progress bars",
    )
    p.set_defaults(func=_train)


def _train(args: argparse.Namespace) -> int:
    from beadsight.train.trainer import resolve_train_config, train

    names = set(TrainConfig.__dataclass_fields__) | set(TrainConfig._renamed)  # old names warn
    overrides = {k: v for k, v in vars(args).items() if k in names}
    config = resolve_train_config(overrides, args.config)
    run = train(config)
    if os.environ.get("RANK", "0") != "0":  # under torchrun, rank 0 reports
        return 0
    print(f"run folder: {run}")
    print(f"  best checkpoint: {run / 'best.pt'}")
    print(f"  last checkpoint: {run / 'last.pt'}")
    return 0
