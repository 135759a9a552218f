"""The files a calibration leaves besides ``model.pt``: ``metrics.json`` (the calibrated
model's metrics on the test presses, the base model's zero-shot and aligned ones, and the
calibration record), ``learning_curve.png`` and ``report.html``, a page built by the one
report builder (:mod:`beadsight.evaluation.report`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from beadsight.evaluation.evaluate import write_metrics_json
from beadsight.evaluation.plots import (
    CurvePoint,
    learning_curve_caption,
    plot_learning_curve,
)
from beadsight.evaluation.report import (
    Figure,
    Report,
    evaluation_figures,
    evaluation_links,
    evaluation_summary,
    write_report,
)
from beadsight.metrics import PAPER_METRICS
from beadsight.train.calibrate_config import (
    ALIGNED_FILE,
    CURVE_PLOT,
    METRICS_FILE,
    MODEL_FILE,
    REPORT_FILE,
    TRAIN_FOLDER,
)
from beadsight.train.run import METRICS_FILE as TRAIN_METRICS

STAGE_NAMES = {"zero_shot": "base model, zero-shot", "aligned": "alignment only"}
DESCRIPTIONS = {
    "model": "the calibrated model (load it with predict, evaluate or live)",
    "aligned": "the base model after the zero-press alignment only",
    "learning_curve": "the learning curve (PNG)",
    "train": "the fine-tuning's log (its run folder also holds config, split, checkpoints)",
}


def validation_curve(out: Path) -> tuple[np.ndarray, np.ndarray, int | None]:
    """(time s, val MAE kPa, index of the kept checkpoint) of the fine-tuning's validations."""
    path = out / TRAIN_FOLDER / TRAIN_METRICS
    if not path.is_file():
        return np.zeros(0), np.zeros(0), None
    lines = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    vals = [x for x in lines if x.get("event") == "val" and x.get("val_loss") is not None]
    if not vals:
        return np.zeros(0), np.zeros(0), None
    losses = [x["val_loss"] for x in vals]
    return (
        np.array([x["time_s"] for x in vals], dtype=float),
        np.array([x["val_mae_kpa"] for x in vals], dtype=float),
        int(np.argmin(losses)),
    )


def write_outputs(out: Path, final: dict, stages: dict, record: dict) -> dict:
    """Write metrics.json, learning_curve.png and report.html; returns the metrics dict."""
    trained = len(record["presses"]["train"]) if record["fine_tuning"] else 0
    points = [
        CurvePoint(STAGE_NAMES["zero_shot"], 0, stages["zero_shot"]["force_error_pct"]),
        CurvePoint(STAGE_NAMES["aligned"], 0, stages["aligned"]["force_error_pct"]),
        CurvePoint("calibrated", trained, final.get("force_error_pct")),
    ]
    times, maes, kept = validation_curve(out)
    plot_learning_curve(
        points, times, maes, kept, PAPER_METRICS["force_error_pct"], out / CURVE_PLOT
    )
    files = {
        **final.get("files", {}),
        "learning_curve": CURVE_PLOT,
        "model": MODEL_FILE,
        "aligned": ALIGNED_FILE,
        "report": REPORT_FILE,
    }
    if record["fine_tuning"]:
        files["train"] = f"{TRAIN_FOLDER}/{TRAIN_METRICS}"
    metrics = {
        **final,
        "files": files,
        "stages": {**stages, "calibrated": {k: final.get(k) for k in stages["zero_shot"]}},
        "calibration": record,
    }
    write_metrics_json(metrics, out / METRICS_FILE)
    write_report(calibration_report(metrics, record, files), out, name=REPORT_FILE)
    return metrics


def calibration_report(metrics: dict, record: dict, files: dict) -> Report:
    presses = record["presses"]
    config = record["config"]
    tuning = record["fine_tuning"]
    how = (
        f"fine-tuned from the {record['alignment'].get('fine_tune_from', 'aligned')} model "
        f"(the lower MAE on the early-stopping presses; {config['layers']} layers, "
        f"lr {config['lr']:g} cosine, "
        f"{tuning['steps']} steps in {tuning['budget_min']:.1f} min) on {len(presses['train'])} "
        f"presses, keeping the checkpoint of lowest loss on {len(presses['val'])} "
        "early-stopping presses"
        if tuning
        else "aligned only (no fine-tuning: --layers none)"
    )
    summary = (
        f"The base model {Path(record['base']).name} was calibrated to the sensor of "
        f"{Path(config['data']).name}: zero-press alignment on {record['alignment']['count']} "
        f"{record['alignment']['frames']}, then {how}"
        + (f", then a force gain of {record['force_gain']:.3f}" if config["gain"] else "")
        + f"; {record['seconds']:.0f} s of a {config['budget_min']:g} min budget. "
        + evaluation_summary(metrics)
    )
    notes = [
        "The columns 'base model, zero-shot' and 'alignment only' are the base model as it came "
        "and after the zero-press alignment, on the same test presses and frames.",
        f"Test presses (never trained on, never used to stop early): {presses['test']}.",
        "coverage: the share of the test presses' valid frames evaluated; every frame with "
        f"a full window of real history counts ({100 * metrics.get('window_coverage', 0):.1f} %).",
    ]
    figures = [
        *evaluation_figures(files, metrics),
        Figure(CURVE_PLOT, "Learning curve", learning_curve_caption()),
    ]
    return Report(
        title=f"Calibration: {Path(config['data']).name}",
        summary=summary,
        metrics=metrics,
        baselines={STAGE_NAMES[k]: v for k, v in metrics["stages"].items() if k in STAGE_NAMES},
        notes=notes,
        figures=figures,
        files=evaluation_links({k: v for k, v in files.items() if k != "report"}, DESCRIPTIONS),
    )
