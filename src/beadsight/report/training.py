"""The learning curve of a training run: training and validation loss, and the validation
MAE, against the optimizer step, read from the run's ``metrics.jsonl``.

``beadsight train`` (and the fine-tuning of ``beadsight calibrate``) append one JSON line
per log event to :data:`TRAINING_LOG` in the run folder: ``event`` ``"train"`` lines carry
the mean training loss since the last line, ``"val"`` lines the validation loss and MAE
(kPa). A checkpoint evaluated from its run folder (``best.pt``, ``last.pt``) gets this
curve in its report.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from beadsight.report.plots import new_figure, save_figure

log = logging.getLogger(__name__)

TRAINING_LOG = (
    "metrics.jsonl"  # a run folder's log: beadsight.train.run.METRICS_FILE (a test checks)
)
MAX_LOG_BYTES = 64 * 1024 * 1024  # a longer log is not read for the curve (about 300k lines)
MIN_POINTS = 2  # a curve needs at least two points of one kind


@dataclass(frozen=True)
class TrainingCurve:
    """The points of a run's log: (step, value) arrays, in the log's order."""

    train_step: np.ndarray
    train_loss: np.ndarray
    val_step: np.ndarray
    val_loss: np.ndarray
    val_mae_kpa: np.ndarray

    @property
    def points(self) -> int:
        """The larger of the training and validation point counts."""
        return max(self.train_step.size, self.val_step.size)


def _number(value: object) -> float:
    return (
        float(value) if isinstance(value, int | float) and not isinstance(value, bool) else np.nan
    )


def read_training_curve(path: Path) -> TrainingCurve | None:
    """The curve in the log at ``path``, or None if there is none (no file, too long, or no
    line with a step and a loss). Lines that are not JSON objects (a line cut short by a
    kill) are skipped."""
    if not path.is_file() or path.stat().st_size > MAX_LOG_BYTES:
        return None
    train: list[tuple[float, float]] = []
    val: list[tuple[float, float, float]] = []
    for text in path.read_text(errors="replace").splitlines():
        try:
            line = json.loads(text)
        except json.JSONDecodeError:
            continue
        if not isinstance(line, dict):
            continue
        step = _number(line.get("step"))
        if line.get("event") == "train" and np.isfinite(step):
            loss = _number(line.get("train_loss"))
            if np.isfinite(loss):
                train.append((step, loss))
        elif line.get("event") == "val" and np.isfinite(step):
            loss, mae = _number(line.get("val_loss")), _number(line.get("val_mae_kpa"))
            if np.isfinite(loss) or np.isfinite(mae):
                val.append((step, loss, mae))
    if not train and not val:
        return None
    t = np.array(train, np.float64).reshape(-1, 2)
    v = np.array(val, np.float64).reshape(-1, 3)
    return TrainingCurve(t[:, 0], t[:, 1], v[:, 0], v[:, 1], v[:, 2])


def training_curve_figure(curve: TrainingCurve) -> Figure:
    """Left: training loss (line) and validation loss (dots) against the step, log scale;
    right: the validation MAE (kPa) against the step, its lowest circled."""
    fig = new_figure(8.0, 3.2)
    left, right = fig.subplots(1, 2)
    fig.subplots_adjust(left=0.11, right=0.98, bottom=0.16, top=0.9, wspace=0.32)
    if curve.train_step.size:
        left.plot(curve.train_step, curve.train_loss, "-", color="tab:blue", label="training")
    finite = np.isfinite(curve.val_loss)
    if finite.any():
        left.plot(
            curve.val_step[finite],
            curve.val_loss[finite],
            "o-",
            ms=4,
            color="tab:red",
            label="validation",
        )
    if (curve.train_loss > 0).all() and (curve.val_loss[finite] > 0).all():
        left.set_yscale("log")
    left.set_xlabel("optimizer step")
    left.set_ylabel("loss (MSE, kPa / output scale)")
    left.legend(fontsize=7)
    left.grid(alpha=0.3)
    mae = np.isfinite(curve.val_mae_kpa)
    if mae.any():
        steps, values = curve.val_step[mae], curve.val_mae_kpa[mae]
        right.plot(steps, values, "o-", ms=4, color="tab:red")
        best = int(np.argmin(values))
        right.plot(steps[best], values[best], "o", mfc="none", ms=11, color="black")
        right.set_ylim(bottom=0)
    else:
        right.text(0.5, 0.5, "no validation", ha="center", va="center", transform=right.transAxes)
    right.set_xlabel("optimizer step")
    right.set_ylabel("validation MAE (kPa)")
    right.grid(alpha=0.3)
    return fig


def write_training_curve(log_path: Path, path: Path) -> bool:
    """Draw the learning curve of the training log ``log_path`` to ``path``; False (nothing
    written) where there is no such log or it has fewer than :data:`MIN_POINTS` points."""
    curve = read_training_curve(log_path)
    if curve is None or curve.points < MIN_POINTS:
        return False
    save_figure(training_curve_figure(curve), path)
    log.info("learning curve of %s: %s", log_path, path)
    return True


def training_curve_caption() -> str:
    return (
        "The learning curve of the run that trained this checkpoint (its metrics.jsonl). "
        "Left: the training loss (blue, the mean since the previous point) and the validation "
        "loss (red dots) against the optimizer step, on a log scale; a validation loss rising "
        "while the training loss falls is overfitting. Right: the validation pressure MAE "
        "(kPa) at each validation; the black circle marks the lowest (best.pt keeps the step "
        "of lowest validation loss, usually the same)."
    )
