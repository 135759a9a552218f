"""The files a calibration leaves besides ``model.pt``: ``metrics.json`` (the kept model's
metrics on the test presses, every candidate's figures and the calibration record),
``learning_curve.png``, ``training_curve.png`` (the kept fine-tuning's losses and MAE by step,
where it validated twice or more) and ``report.html``, a page built by the one report builder
(:mod:`beadsight.report.page`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from beadsight.calibrate.candidates import METRIC_KEYS, Candidate
from beadsight.calibrate.config import (
    ALIGNED_FILE,
    CURVE_PLOT,
    METRICS_FILE,
    MODEL_FILE,
    REPORT_FILE,
    REST_FILE,
    TRAIN_FOLDER,
)
from beadsight.evaluation.breakdown import TRAINING_PLOT
from beadsight.evaluation.evaluate import write_metrics_json
from beadsight.report.page import (
    Figure,
    Report,
    evaluation_figures,
    evaluation_links,
    evaluation_summary,
    press_tables,
    write_report,
)
from beadsight.report.paper import PAPER_METRICS
from beadsight.report.plots import CurvePoint, learning_curve_caption, plot_learning_curve
from beadsight.report.training import write_training_curve
from beadsight.train.run import METRICS_FILE as TRAIN_METRICS

CANDIDATE_NAMES = {
    "zero-shot": "base model, zero-shot",
    "zero-press": "zero-press (rest statistics)",
    "decoder": "fine-tuned decoder",
    "all": "fine-tuned, all layers",
    "scratch": "small model from scratch",
}
DESCRIPTIONS = {
    "model": "the calibrated model (load it with predict, evaluate or live)",
    "aligned": "the zero-press candidate: the base model with the new pouch's rest statistics",
    "rest": "the new pouch's rest reference (the rest file of live --rest and calibrate --rest)",
    "learning_curve": "the learning curve (PNG)",
    "train": "the kept fine-tuning's log (its run folder also holds config, split, checkpoints)",
}


def validation_curve(run: Path) -> tuple[np.ndarray, np.ndarray, int | None]:
    """(time s, val MAE kPa, index of the kept checkpoint) of a fine-tuning's validations."""
    path = run / TRAIN_METRICS
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


def no_fine_tuning_reason(record: dict) -> str | None:
    """Why no fine-tuning step was taken (None if one was): the line the command and the
    report print."""
    if record["fine_tuned"]:
        return None
    if record["presses_used"] == 0:
        return "no fine-tuning: no presses were used (--presses 0, rest frames only)"
    skipped = [
        f"{n}: {c['status'].removeprefix('skipped: ')}"
        for n, c in record["candidates"].items()
        if c["status"].startswith("skipped")
    ]
    return "no fine-tuning happened (0 steps). " + "; ".join(skipped or ["every run took 0 steps"])


def write_outputs(
    out: Path, final: dict | None, cands: dict[str, Candidate], chosen: str, record: dict
) -> dict:
    """Write metrics.json, learning_curve.png and report.html; returns the metrics dict."""
    record["no_fine_tuning"] = no_fine_tuning_reason(record)
    trained = len(record.get("presses", {}).get("train", [])) if record["fine_tuned"] else 0
    points = [
        CurvePoint(CANDIDATE_NAMES[n], trained if cands[n].steps else 0, c.test["force_error_pct"])
        for n, c in cands.items()
        if c.test
    ]
    times, maes, kept = validation_curve(out / TRAIN_FOLDER / chosen)
    plot_learning_curve(
        points, times, maes, kept, PAPER_METRICS["force_error_pct"], out / CURVE_PLOT
    )
    files = {
        **(final or {}).get("files", {}),
        "learning_curve": CURVE_PLOT,
        "model": MODEL_FILE,
        "aligned": ALIGNED_FILE,
        "report": REPORT_FILE,
    }
    if record["rest_file"]:
        files["rest"] = REST_FILE
    if cands[chosen].steps:
        files["train"] = f"{TRAIN_FOLDER}/{chosen}/{TRAIN_METRICS}"
        if write_training_curve(out / TRAIN_FOLDER / chosen / TRAIN_METRICS, out / TRAINING_PLOT):
            files["training_curve"] = TRAINING_PLOT  # the fine-tuning's loss and MAE by step
    empty = {k: None for k in METRIC_KEYS}
    metrics = {
        **(final or empty),
        "files": files,
        "candidates": record["candidates"],
        "chosen": chosen,
        "calibration": record,
    }
    write_metrics_json(metrics, out / METRICS_FILE)
    write_report(calibration_report(metrics, record, files, final is not None), out, REPORT_FILE)
    return metrics


def _how(record: dict) -> str:
    config, chosen = record["config"], record["chosen"]
    cand = record["candidates"][chosen]
    if record["presses_used"] == 0:
        return (
            "No presses were used: this is a zero-press calibration from rest frames only "
            f"({record['alignment']['count']} {record['alignment']['frames']}). "
        )
    text = (
        f"{record['presses_used']} presses were used ({len(record['presses']['train'])} to "
        f"train on, {len(record['presses']['val'])} to choose by). Kept: "
        f"{CANDIDATE_NAMES[chosen]}, the lowest MAE on the early-stopping presses"
    )
    if cand["steps"]:
        text += f" ({cand['steps']} steps, the checkpoint of step {cand['best_step']})"
    text += "."
    if config["gain"]:
        text += f" Force gain {record['force_gain']:.3f}."
    return text + " "


def calibration_report(metrics: dict, record: dict, files: dict, scored: bool) -> Report:
    config, budget = record["config"], record["budget"]
    summary = (
        f"The base model {Path(record['base']).name} was calibrated to the pouch of "
        f"{Path(config['data'] or config['rest']).name}. {_how(record)}"
        + (f"{record['no_fine_tuning'].capitalize()}. " if record["no_fine_tuning"] else "")
        + f"It took {budget['seconds']:.0f} s of a {config['budget_min']:g} min budget. "
        + (evaluation_summary(metrics) if scored else "It was not scored on any press.")
    )
    notes = [_candidate_line(n, c, n == record["chosen"]) for n, c in record["candidates"].items()]
    if "presses" in record:
        notes.append(
            f"Test presses (never trained on, never used to choose): {record['presses']['test']}."
        )
    if scored:
        notes.append(
            "coverage: the share of the test presses' valid frames evaluated "
            f"({100 * (metrics.get('coverage') or 0):.1f} %; every candidate on the same frames)."
        )
    figures = [*(evaluation_figures(files, metrics) if scored else [])]
    figures.append(Figure(CURVE_PLOT, "Learning curve", learning_curve_caption()))
    baselines = {
        CANDIDATE_NAMES[n]: c["test"]
        for n, c in record["candidates"].items()
        if c["test"] and n != record["chosen"]
    }
    return Report(
        title=f"Calibration: {Path(config['data'] or config['rest']).name}",
        summary=summary,
        metrics=metrics if scored else None,
        baselines=baselines,
        notes=notes,
        figures=figures,
        tables=press_tables(metrics),
        files=evaluation_links({k: v for k, v in files.items() if k != "report"}, DESCRIPTIONS),
    )


def _candidate_line(name: str, c: dict, chosen: bool) -> str:
    """One note per candidate: status, time, steps, early-stopping and test figures."""

    def short(m: dict | None) -> str:
        if not m or m.get("mae_kpa") is None:
            return "-"
        force = m.get("force_error_pct")
        return f"MAE {m['mae_kpa']:.3f} kPa, force " + (
            "n/a" if force is None else f"{force:.1f} %"
        )

    line = f"Candidate {CANDIDATE_NAMES[name]}{' (kept)' if chosen else ''}: {c['status']}"
    if c["budget_s"]:
        line += f"; {c['steps']} steps, {c['seconds']:.0f} s of a {c['budget_s']:.0f} s share"
    if c["status"] == "scored":
        line += f"; early-stopping presses {short(c['val'])}; test presses {short(c['test'])}"
    return line + "".join(f"; {n}" for n in c["notes"]) + "."
