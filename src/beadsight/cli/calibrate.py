"""The calibration command: ``beadsight calibrate --data D --out OUT [...]`` fits the base
model to a new sensor (docs/calibration.md)."""

from __future__ import annotations

import argparse

from beadsight.cli.options import MINUTES


def register(commands) -> None:
    commands.add("calibrate", _calibrate, _calibrate_arguments)


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
    choices = {"candidates": {"choices": CANDIDATES}}
    rows = [
        (name, help, {**(extra[0] if extra else {}), **choices.get(name, {})})
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
    """The test figures of every scored candidate beside the paper's; each fine-tuning's
    steps, and why a candidate was not scored."""
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
        elif c["steps"]:  # a fine-tuning: how long it trained
            print(
                f"{name}: "
                + "; ".join([f"{c['steps']} steps in {c['seconds']:.0f} s", *c["notes"]])
            )


def _num(value) -> str:
    return f"{value:10.3f}" if isinstance(value, (int, float)) else f"{'n/a':>10s}"
