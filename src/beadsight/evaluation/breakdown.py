"""An evaluation broken down: per press, and by the true force.

:class:`Breakdown` collects, batch by batch, the paper's metrics of each press (a
:class:`~beadsight.evaluation.metrics.MetricsAccumulator` per press, so a press's row is
exactly what :func:`~beadsight.evaluation.metrics.compute_metrics` gives on its frames) and
each frame's true and predicted total force (16 bytes a frame). Its :meth:`Breakdown.result`
goes into ``metrics.json``:

* ``per_press``: one row per press, worst first (the highest total-force error, then the
  highest MAE): press, frames, position, peak true force, force error, CoP error, IoU, MAE;
* ``force_error_by_force``: the total-force error binned by the true force, with counts.

:func:`write_breakdown_files` writes ``presses.csv`` (the rows), ``force_scatter.png``
(predicted against true force), ``force_error.png`` (the error against force) and, where
the checkpoint sits in a training run folder, ``training_curve.png`` (its ``metrics.jsonl``).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import fields
from pathlib import Path

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.files import atomic_write_text
from beadsight.metrics import FrameMetrics, MetricsAccumulator
from beadsight.report.force_plots import plot_force_error, plot_force_scatter
from beadsight.report.training import TRAINING_LOG, write_training_curve

FORCE_BINS = 8  # equal-width bins of the true force, 0 N to the largest
PRESS_COLUMNS = (  # the per-press table: key, as in metrics.json and presses.csv
    "press",
    "frames",
    "x_mm",
    "y_mm",
    "peak_force_n",
    "force_error_pct",
    "cop_error_mm",
    "iou",
    "mae_kpa",
)
PRESSES_CSV = "presses.csv"
SCATTER_PLOT = "force_scatter.png"
FORCE_ERROR_PLOT = "force_error.png"
TRAINING_PLOT = "training_curve.png"


def _subset(fm: FrameMetrics, mask: np.ndarray) -> FrameMetrics:
    return FrameMetrics(**{f.name: getattr(fm, f.name)[mask] for f in fields(fm)})


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


class Breakdown:
    """Per-press metrics and per-frame forces of one evaluation, added batch by batch."""

    def __init__(self, geometry: SensorGeometry):
        self.geometry = geometry
        self.presses: dict[int, MetricsAccumulator] = {}
        self.position_sum: dict[int, np.ndarray] = {}
        self.peak: dict[int, float] = {}
        self.force_gt: list[np.ndarray] = []
        self.force_pred: list[np.ndarray] = []

    def add(self, fm: FrameMetrics, press_id: np.ndarray, position_mm: np.ndarray) -> None:
        """fm: a batch's per-frame metrics; press_id (B,) int; position_mm (B, 2) mm."""
        self.force_gt.append(np.asarray(fm.force_gt_n, np.float64))
        self.force_pred.append(np.asarray(fm.force_pred_n, np.float64))
        for press in np.unique(press_id).tolist():
            mask = press_id == press
            acc = self.presses.setdefault(press, MetricsAccumulator(self.geometry))
            acc.add(_subset(fm, mask))
            total = self.position_sum.get(press, np.zeros(2))
            self.position_sum[press] = total + position_mm[mask].sum(axis=0)
            self.peak[press] = max(self.peak.get(press, 0.0), float(fm.force_gt_n[mask].max()))

    def forces(self) -> tuple[np.ndarray, np.ndarray]:
        """(true, predicted) total force of every frame added, N, in order."""
        if not self.force_gt:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(self.force_gt), np.concatenate(self.force_pred)

    def rows(self) -> list[dict]:
        """One row per press (keys :data:`PRESS_COLUMNS`), worst first."""
        rows = []
        for press, acc in self.presses.items():
            m = acc.result()
            x, y = (self.position_sum[press] / acc.frames).tolist()
            rows.append(
                {
                    "press": int(press),
                    "frames": m["frames"],
                    "x_mm": _finite(x),
                    "y_mm": _finite(y),
                    "peak_force_n": _finite(self.peak[press]),
                    **{k: m[k] for k in ("force_error_pct", "cop_error_mm", "iou", "mae_kpa")},
                }
            )

        def worst_first(row: dict) -> tuple:
            err = row["force_error_pct"]
            return (err is None, -(err or 0.0), -(row["mae_kpa"] or 0.0), row["press"])

        return sorted(rows, key=worst_first)

    def result(self) -> dict:
        """``per_press`` and ``force_error_by_force`` for metrics.json (strict JSON)."""
        gt, pred = self.forces()
        return {"per_press": self.rows(), "force_error_by_force": force_error_by_force(gt, pred)}


def force_error_by_force(gt_n: np.ndarray, pred_n: np.ndarray, bins: int = FORCE_BINS) -> dict:
    """The total-force error binned by true force, over frames with ``F_gt > 0`` (those
    the force error counts). gt_n, pred_n: (N,) N.

    returns: ``edges_n`` (bins + 1 edges, 0 N to the largest true force), per bin
    ``frames``, ``abs_error_n`` (mean ``|F_pred - F_gt|``, N), ``error_pct``
    (``100 * sum|F_pred - F_gt| / sum F_gt``, the overall metric's definition) and
    ``bias_n`` (mean ``F_pred - F_gt``, N); None where a bin has no frames.
    """
    gt, pred = np.asarray(gt_n, np.float64), np.asarray(pred_n, np.float64)
    keep = gt > 0
    gt, pred = gt[keep], pred[keep]
    top = float(gt.max()) if gt.size else 1.0
    edges = np.linspace(0.0, top, bins + 1)
    which = np.clip(np.searchsorted(edges, gt, side="right") - 1, 0, bins - 1)
    out: dict[str, list] = {"edges_n": edges.tolist(), "frames": [], "abs_error_n": []}
    out |= {"error_pct": [], "bias_n": []}
    for b in range(bins):
        g, p = gt[which == b], pred[which == b]
        out["frames"].append(int(g.size))
        if not g.size:
            out["abs_error_n"].append(None)
            out["error_pct"].append(None)
            out["bias_n"].append(None)
            continue
        out["abs_error_n"].append(_finite(np.abs(p - g).mean()))
        out["error_pct"].append(_finite(100 * np.abs(p - g).sum() / g.sum()))
        out["bias_n"].append(_finite((p - g).mean()))
    return out


def press_csv(rows: list[dict]) -> str:
    """The per-press rows as CSV text (a header of :data:`PRESS_COLUMNS`; empty: n/a)."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(PRESS_COLUMNS)
    for row in rows:
        writer.writerow(["" if row[k] is None else row[k] for k in PRESS_COLUMNS])
    return text.getvalue()


def write_breakdown_files(out: Path, breakdown: Breakdown, metrics: dict) -> dict[str, str]:
    """Write presses.csv, force_scatter.png, force_error.png and (when the checkpoint's
    folder holds its training log) training_curve.png; returns {role: file name}."""
    atomic_write_text(out / PRESSES_CSV, press_csv(breakdown.rows()))
    files = {"presses": PRESSES_CSV}
    gt, pred = breakdown.forces()
    if gt.size:
        plot_force_scatter(gt, pred, out / SCATTER_PLOT)
        plot_force_error(metrics["force_error_by_force"], out / FORCE_ERROR_PLOT)
        files.update(force_scatter=SCATTER_PLOT, force_error=FORCE_ERROR_PLOT)
    checkpoint = metrics.get("checkpoint")
    log = Path(checkpoint).parent / TRAINING_LOG if checkpoint else None
    if log is not None and write_training_curve(log, out / TRAINING_PLOT):
        files["training_curve"] = TRAINING_PLOT
    return files
