"""Training commands: ``beadsight train --data D --out RUN [...]`` and ``beadsight calibrate``."""

from __future__ import annotations

import argparse
import os

from beadsight.cli.options import MAX_BUDGET_MIN, Number

MINUTES = Number(float, positive=True, high=MAX_BUDGET_MIN)  # budgets and intervals

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
        "color_jitter",
        "random colour, contrast and brightness changes of each training input, 0..1 "
        "(for models meant for pouches of other looks)",
        {"type": float},
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
    commands.add("calibrate", _calibrate, _calibrate_arguments)


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


# --- calibrate ---------------------------------------------------------------------------
CALIBRATE_FLAGS = (
    (
        "base",
        "checkpoint to start from (default: the shipped base model)",
        {"metavar": "CKPT", "type": str},
    ),
    (
        "budget_min",
        "wall-clock budget of the whole calibration, evaluations included, minutes; it ends "
        "within M + 10 %% (see 'budgets' below)",
        {"metavar": "M", "type": MINUTES},
    ),
    (
        "rest",
        "the untouched pouch's rest file (.npz, the format of live --rest and health "
        "--save-rest) for the zero-press candidate (default: the presses' pre-contact frames)",
        {"metavar": "REST.npz", "type": str},
    ),
    (
        "presses",
        "use only this many presses (after --skip); 0: calibrate from rest frames only "
        "(--data's pre-contact frames, or --rest), scoring on every press of --data",
        {"type": int, "metavar": "N"},
    ),
    ("skip", "drop the first K presses (break-in)", {"metavar": "K"}),
    ("gain", "fit a per-sensor force gain on the training presses"),
    (
        "candidates",
        "the candidates to try where they make sense for the data and the budget; the "
        "early-stopping presses choose (the base model as it came always competes)",
        {"nargs": "+", "metavar": "NAME"},
    ),
    ("lr", "peak learning rate of fine-tuning (cosine schedule over its time)"),
    ("batch_size", "windows per step"),
    ("augment", "augment with the 8 dihedral transforms (off: measured better for one pouch)"),
    ("seed", "seed of the split and the batch order"),
    ("device", "auto, cpu, cuda, cuda:N or mps"),
    ("overwrite", "replace an earlier calibration in --out"),
    ("progress", "no progress bars"),
)


def _calibrate_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.calibrate.config import (
        CANDIDATES,
        SMALLEST_USEFUL_BUDGET_MIN,
        CalibrateConfig,
    )
    from beadsight.cli.options import add_fields

    p.add_argument(
        "--data",
        default=None,
        help="the new sensor's presses (.h5, ours or the reference's); with --presses 0 "
        "and --rest it may be left out (then nothing is scored)",
    )
    p.add_argument(
        "--out", required=True, help="output folder: model.pt, metrics.json, report.html"
    )
    rows = [
        (
            name,
            help,
            {**(extra[0] if extra else {}), **_choices({"candidates": CANDIDATES}, name)},
        )
        for name, help, *extra in CALIBRATE_FLAGS
    ]
    add_fields(p, CalibrateConfig, rows)
    p.epilog = (
        f"budgets: below {SMALLEST_USEFUL_BUDGET_MIN:g} min on a 2-core CPU (the shipped base "
        "model, 30 presses; measured) no fine-tuning fits: the evaluations take the budget, "
        "only the base model and the zero-press candidate compete, and the command says so. "
        "A few minutes buy a few dozen steps; the default 10 min is what the recipe was "
        "measured with."
    )


def _calibrate(args: argparse.Namespace) -> int:
    """Fit the base model to a new sensor from a few of its presses.

    Tries the candidates that make sense for the data within one wall-clock budget:
    zero-press (normalisation from rest frames), fine-tuning the decoder or all layers,
    a small model from scratch; keeps the best on held-out early-stopping presses.
    Writes OUT/model.pt, OUT/metrics.json and OUT/report.html: every candidate's figures
    on test presses of this sensor beside the paper's.
    """
    import time

    started = time.monotonic()  # the budget counts from here, torch's import included
    from beadsight.calibrate.config import REPORT_FILE, CalibrateConfig
    from beadsight.calibrate.run import calibrate
    from beadsight.cli.options import field_values

    metrics = calibrate(CalibrateConfig(**field_values(args, CalibrateConfig)), started)
    _print_candidates(metrics)
    record = metrics["calibration"]
    if record["no_fine_tuning"]:
        print(record["no_fine_tuning"].upper()[:1] + record["no_fine_tuning"][1:])
    budget = record["budget"]
    print(
        f"kept: {metrics['chosen']}; {budget['seconds']:.0f} s of a "
        f"{budget['budget_s']:.0f} s budget"
    )
    if metrics.get("coverage") is not None:
        print(f"coverage {100 * metrics['coverage']:.1f} % of the test presses' valid frames")
    else:
        print("not scored on any press (no --data, or no time left to score)")
    print(f"model: {args.out}/model.pt; report: {args.out}/{REPORT_FILE}")
    return 0


def _print_candidates(metrics: dict) -> None:
    """The test figures of every scored candidate beside the paper's."""
    cands = {n: c for n, c in metrics["candidates"].items() if c["test"]}
    print(f"{'test presses':22s} " + " ".join(f"{n:>10s}" for n in cands) + f" {'paper':>8s}")
    for key, label in (
        ("mae_kpa", "MAE (kPa)"),
        ("force_error_pct", "force error (%)"),
        ("cop_error_mm", "CoP error (mm)"),
        ("iou", "contact IoU"),
        ("worst_region_mae_kpa", "worst region (kPa)"),
    ):
        row = [c["test"].get(key) for c in cands.values()]
        row.append(metrics["paper"].get(key) if "paper" in metrics else None)
        print(f"{label:22s} " + " ".join(_num(v) for v in row))
    for name, c in metrics["candidates"].items():
        if c["status"] != "scored" or not c["test"]:
            print(f"{name}: " + "; ".join([c["status"], *c["notes"]]))


def _num(value) -> str:
    return f"{value:10.3f}" if isinstance(value, (int, float)) else f"{'n/a':>10s}"
