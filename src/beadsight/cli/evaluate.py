"""``beadsight evaluate`` and ``beadsight predict``: argument parsing only."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(commands) -> None:
    commands.add("evaluate", run_evaluate, _evaluate_arguments)
    commands.add("predict", run_predict, _predict_arguments)


def _evaluate_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_option
    from beadsight.evaluation import config

    p.add_argument("--checkpoint", required=True, type=Path, help="checkpoint file (.pt)")
    p.add_argument("--data", required=True, type=Path, help="dataset file (HDF5)")
    add_option(
        p,
        "--split",
        config.DEFAULT_SPLIT,
        "presses to evaluate (test/val: the training run's split)",
        choices=config.SPLIT_CHOICES,
    )
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument(
        "--overwrite", action="store_true", help="write into a --out folder that is not empty"
    )
    _batch_and_device(p, config.EVALUATE_BATCH_SIZE)
    p.add_argument(
        "--max-frames",
        type=int,
        default=None,
        help="evaluate only N frames spread evenly over the split (a quick estimate)",
    )
    p.add_argument(
        "--baselines",
        action="store_true",
        help="also score an all-zero map and the mean training label",
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument(
        "--resize",
        action="store_true",
        help="resize frames to the checkpoint's image size if it differs from the dataset's "
        "(for checkpoints trained with --image-size)",
    )
    _runtime_arguments(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _runtime_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.evaluation import config

    p.add_argument(
        "--backend",
        default=config.DEFAULT_BACKEND,
        choices=config.BACKEND_CHOICES,
        help="the runtime that runs the model, as `live --backend` (exported and quantized "
        "models are scored on the same metrics; default: %(default)s)",
    )
    p.add_argument(
        "--precision",
        default="auto",
        choices=config.PRECISION_CHOICES,
        help="runtime precision (auto: the backend's own)",
    )


def _predict_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_option
    from beadsight.evaluation import config

    p.add_argument("--checkpoint", required=True, type=Path, help="checkpoint file (.pt)")
    p.add_argument("--input", required=True, type=Path, help="dataset (HDF5) or video file")
    p.add_argument("--out", required=True, type=Path, help="output file (.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    add_option(
        p,
        "--preprocess",
        config.PREDICT_PREPROCESS,
        "auto, none, reference, reference-linear, or a fisheye lens .json (video input only)",
    )
    p.add_argument(
        "--rest",
        type=Path,
        default=None,
        help="rest-referenced models: a rest file (.npz, as `health --save-rest` and `live` "
        "write; its image at the model's size); default: a dataset's own rest frames, or the "
        "average of a video's first frames",
    )
    _batch_and_device(p, config.PREDICT_BATCH_SIZE)
    _runtime_arguments(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _batch_and_device(p: argparse.ArgumentParser, batch_size: int) -> None:
    from beadsight.cli.options import add_option
    from beadsight.evaluation.config import DEFAULT_DEVICE

    add_option(p, "--batch-size", batch_size, "frames per batch")
    add_option(p, "--device", DEFAULT_DEVICE, "auto, cpu, cuda, cuda:1, mps, ...")


def run_evaluate(args: argparse.Namespace) -> int:
    """Metrics of a checkpoint on a dataset split, beside the paper's figures.

    Run a checkpoint over a dataset split; write metrics.json, predictions.h5 and PNG
    plots to --out and print the metrics beside the paper's.
    """
    from beadsight.evaluation.config import EvaluateConfig
    from beadsight.evaluation.evaluate import evaluate
    from beadsight.files import prepare_output_folder
    from beadsight.report.paper import format_metrics_table

    prepare_output_folder(args.out, args.overwrite)
    config = EvaluateConfig(
        split=args.split,
        backend=args.backend,
        precision=args.precision,
        device=args.device,
        batch_size=args.batch_size,
        max_frames=args.max_frames,
        baselines=args.baselines,
        plots=not args.no_plots,
        resize=args.resize,
        progress=not args.no_progress,
    )
    metrics = evaluate(args.checkpoint, args.data, config, args.out)
    presses = metrics["presses"]
    print(
        f"{metrics['split']} split ({metrics['split_source']}): {metrics['frames']} frames of "
        f"{presses} press{'es' if presses != 1 else ''}, {metrics['checkpoint']} "
        f"({metrics['backend']}) on {metrics['dataset']}"
    )
    rest = ", or a rest image before it" if metrics["model_config"].get("rest_input") else ""
    print(
        f"coverage: {metrics['coverage']:.1%} of the split's {metrics['valid_frames']} valid "
        f"frames (the others lack a full window of valid history{rest}, or --max-frames "
        "skipped them)"
    )
    print(format_metrics_table(metrics, metrics.get("baselines")))
    print(f"wrote {args.out}: " + ", ".join(metrics.get("files", {}).values()))
    return 0


def run_predict(args: argparse.Namespace) -> int:
    """Pressure maps, force and centre of pressure for every frame of a recording.

    Run a checkpoint over a dataset or a video file and write per-frame pressure maps
    (kPa), total force (N), centre of pressure (mm) and timestamps to HDF5.
    """
    from beadsight.evaluation.predict import predict_recording, summarize_predictions

    out = predict_recording(
        args.checkpoint,
        args.input,
        args.out,
        preprocess=args.preprocess,
        batch_size=args.batch_size,
        device=args.device,
        progress=not args.no_progress,
        rest=args.rest,
        overwrite=args.overwrite,
        backend=args.backend,
        precision=args.precision,
    )
    print(summarize_predictions(out))
    return 0
