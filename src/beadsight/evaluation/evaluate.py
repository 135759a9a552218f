"""Evaluate a checkpoint on a dataset: the paper's metrics, predictions, plots.

:func:`evaluate` runs the model (on the runtime ``EvaluateConfig.backend`` names, torch by
default: the runtimes of live sensing, so exported and int8 models are scored alike) over
every frame of the chosen split that ends a
full window of valid, continuous history (the same frames training samples, via
:func:`beadsight.data.splits.dataset_window_ends`; a window may reach into the
previous press). A rest-referenced model scores only frames with a rest image before
them, and each input gets it by training's rule (:mod:`beadsight.data.rest`, read by
:mod:`beadsight.data.windows`). It compares with the ground truth of
:func:`beadsight.data.labels.label_maps`, and accumulates the metrics of
:mod:`beadsight.metrics` batch by batch. With ``out_dir`` it writes:

* ``metrics.json``: the metrics (strict JSON, no NaN), counts, split, names, and
  ``coverage`` (frames evaluated / valid frames of the split) and ``window_coverage``
  (frames with a full window of history, and for a rest-referenced model a rest image,
  / valid frames);
* ``predictions.h5``: ``pred_kpa``/``gt_kpa`` (N, H, W) float32 (gzip),
  ``force_gt_n``/``force_pred_n`` (N,) N, ``cop_gt_mm``/``cop_pred_mm`` (N, 2) mm
  (NaN where that map has no positive pressure), ``index`` (N,) dataset frame
  index, appended batch by batch under a temporary name (attribute ``rest_source``:
  ``"dataset"`` for a rest-referenced model, else ``"none"``);
* ``examples.png``, ``region_error.png``, ``force_traces.png``, and the breakdown of
  :mod:`beadsight.evaluation.breakdown`: ``presses.csv`` (per press, worst first; also
  ``per_press`` in metrics.json), ``force_scatter.png``, ``force_error.png`` and, for a
  checkpoint in its training run folder, ``training_curve.png``;
* ``index.html``: the report page (:mod:`beadsight.report.page`).

A write that fails (disk full) raises :class:`beadsight.files.WriteError`; no file
is left damaged under its final name (``predictions.h5`` is written as
``predictions.h5.partial`` and removed on failure).

Memory stays bounded by the batch size whatever the dataset's length, but for 16 bytes
a frame (the forces of the scatter) and one row per press. Which
presses or frames form a split: :mod:`beadsight.evaluation.selection`.
"""

from __future__ import annotations

import json
import logging
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from beadsight.checkpoint import PressureModel
from beadsight.config import SensorGeometry
from beadsight.data.dataset import Dataset, open_dataset
from beadsight.data.labels import label_maps
from beadsight.data.windows import WindowReader
from beadsight.evaluation.breakdown import Breakdown, write_breakdown_files
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.predict import IncrementalH5, as_model, open_runtime
from beadsight.evaluation.rest_images import REST_FROM_DATASET, REST_NONE
from beadsight.evaluation.selection import (
    SPLIT_CHOICES,
    EvaluationError,
    SplitSelection,
    coverage,
    evaluation_frames,
    given_presses,
    select_split,
    selection_ends,
    subsample,
)
from beadsight.files import atomic_write_json
from beadsight.inference.backend import Backend
from beadsight.metrics import FrameMetrics, MetricsAccumulator
from beadsight.report.page import REPORT_FILE, evaluation_report, write_report
from beadsight.report.paper import PAPER_METRICS
from beadsight.report.plots import (
    ForceTrace,
    plot_examples,
    plot_force_traces,
    plot_region_errors,
)

log = logging.getLogger(__name__)

__all__ = [
    "SPLIT_CHOICES",
    "EvaluateConfig",
    "EvaluationError",
    "SplitSelection",
    "evaluate",
    "evaluation_frames",
    "evaluation_geometry",
    "select_split",
    "subsample",
    "write_metrics_json",
]
EXAMPLE_PRESSES = 4  # presses shown in examples.png (the frame of peak force of each)
TRACE_PRESSES = 3  # presses shown in force_traces.png
MEAN_MAP_MAX_FRAMES = 4096  # training frames averaged for the mean-map baseline
METRICS_FILE = "metrics.json"
METRICS_FILE_MODE = 0o644  # results are meant to be shared
PREDICTIONS_FILE = "predictions.h5"
EXAMPLES_PLOT = "examples.png"
REGION_PLOT = "region_error.png"
FORCE_PLOT = "force_traces.png"
DEFINITIONS = {
    "mae_kpa": "mean over frames of the mean |pred - gt| over all pixels",
    "force_error_pct": "100 * mean|F_pred - F_gt| / mean F_gt over frames with F_gt > 0; "
    "F = integral of the map",
    "cop_error_mm": "distance between pressure-weighted centroids on frames with F_gt >= 2 N; "
    "an empty prediction is measured from the sensor centre",
    "iou": "Otsu foreground of the prediction vs the true contact (Otsu of the label, = gt > 0 "
    "for hard-edged labels) on frames with F_gt >= 2 N; empty prediction -> 0",
    "region_mae_kpa": "per-frame MAE of all evaluated frames grouped by their press's commanded position on "
    "a 4x4 grid of the field of view; [row][col] in image orientation; null = no frames",
    "per_press": "the metrics above on each press's evaluated frames, worst force error first",
    "force_error_by_force": "force error (as above) and mean |F_pred - F_gt| (N) in equal bins "
    "of F_gt over frames with F_gt > 0; null = no frames in the bin",
}


# --- geometry -----------------------------------------------------------------------
def evaluation_geometry(model: PressureModel, ds: Dataset, resize: bool = False) -> SensorGeometry:
    """The geometry of the evaluated maps: the dataset's, at the model's image size.

    Raises EvaluationError naming both sizes if the model's image size differs from
    the dataset's, unless ``resize`` (frames are then resized to the model's size
    by area averaging, as ``beadsight train --image-size`` does, and labels are
    drawn at that size).
    """
    if model.image_size != ds.image_size and not resize:
        raise EvaluationError(
            f"image_size mismatch: the checkpoint {model.source} expects image_size="
            f"{model.image_size} px frames, but the dataset {ds.path} has {ds.image_size} px "
            "frames (pass --resize to resize the frames to the checkpoint's size)"
        )
    mg, dg = model.geometry, ds.geometry
    if (mg.sensor_size_mm, mg.finger_radius_mm) != (dg.sensor_size_mm, dg.finger_radius_mm):
        log.warning(
            "geometry differs: checkpoint %s has sensor %g mm / finger %g mm, dataset %s has "
            "%g mm / %g mm; labels use the dataset's",
            model.source,
            mg.sensor_size_mm,
            mg.finger_radius_mm,
            ds.path,
            dg.sensor_size_mm,
            dg.finger_radius_mm,
        )
    return dg.with_image_size(model.image_size)


# --- baselines and examples ---------------------------------------------------------
def _labels(ds: Dataset, index: np.ndarray, geometry: SensorGeometry) -> np.ndarray:
    """(B,) frame indices -> (B, S, S) float32 kPa ground truth, S = geometry.image_size_px."""
    return label_maps(ds.force_n[index], ds.position_mm[index], ds.contact[index], geometry)


def mean_gt_map(
    ds: Dataset, index: np.ndarray, geometry: SensorGeometry, batch_size: int
) -> np.ndarray:
    """Mean label over (at most MEAN_MAP_MAX_FRAMES evenly spaced) frames: (S, S) float32 kPa."""
    if index.size > MEAN_MAP_MAX_FRAMES:
        index = index[np.linspace(0, index.size - 1, MEAN_MAP_MAX_FRAMES).astype(np.int64)]
    s = geometry.image_size_px
    total = np.zeros((s, s))
    for i in range(0, index.size, batch_size):
        total += _labels(ds, index[i : i + batch_size], geometry).sum(axis=0, dtype=np.float64)
    return (total / max(index.size, 1)).astype(np.float32)


def _example_frames(ds: Dataset, ends: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` frames, one per press spread over the split: each press's peak force."""
    presses = np.unique(ds.press_id[ends])
    picks = presses[
        np.unique(
            np.linspace(0, presses.size - 1, min(count, presses.size)).round().astype(np.int64)
        )
    ]
    frames = []
    for p in picks:
        candidates = ends[ds.press_id[ends] == p]
        force = np.where(ds.contact[candidates], ds.force_n[candidates], 0.0)
        frames.append(candidates[int(np.argmax(force))])
    return np.asarray(frames, dtype=np.int64)


def _prediction_specs(s: int) -> dict:
    return {
        "pred_kpa": ((s, s), np.float32, True),
        "gt_kpa": ((s, s), np.float32, True),
        "force_gt_n": ((), np.float64, False),
        "force_pred_n": ((), np.float64, False),
        "cop_gt_mm": ((2,), np.float64, False),
        "cop_pred_mm": ((2,), np.float64, False),
        "index": ((), np.int64, False),
    }


# --- the evaluation -----------------------------------------------------------------
@dataclass
class _Collected:
    """Small per-run state for plots: example maps, per-frame forces of traced presses."""

    example_index: np.ndarray
    trace_presses: np.ndarray
    examples: dict
    trace_rows: list
    breakdown: Breakdown  # per press, and each frame's forces


def _collect(col: _Collected, ds: Dataset, batch: np.ndarray, pred, gt, fm: FrameMetrics) -> None:
    for k in np.flatnonzero(np.isin(batch, col.example_index)):
        col.examples[int(batch[k])] = (gt[k].copy(), pred[k].copy())
    for k in np.flatnonzero(np.isin(ds.press_id[batch], col.trace_presses)):
        col.trace_rows.append(
            (int(batch[k]), int(ds.press_id[batch[k]]), fm.force_gt_n[k], fm.force_pred_n[k])
        )
    col.breakdown.add(fm, ds.press_id[batch], ds.position_mm[batch])


def evaluate(
    checkpoint: PressureModel | str | Path,
    data: str | Path,
    config: EvaluateConfig | None = None,
    out_dir: str | Path | None = None,
    *,
    presses: np.ndarray | None = None,
    train_presses: np.ndarray | None = None,
) -> dict:
    """Evaluate ``checkpoint`` on dataset ``data`` as ``config`` says; returns the metrics dict.

    The model runs on the runtime ``config.backend`` (the runtimes of live sensing,
    :func:`~beadsight.evaluation.predict.open_runtime`), so an exported or quantized
    model is scored on the paper's metrics. The dict holds mae_kpa, force_error_pct,
    cop_error_mm, iou (0..1), region_mae_kpa (4x4, None for empty cells),
    worst_region_mae_kpa, frames and per-metric frame counts (see
    :meth:`beadsight.metrics.MetricsAccumulator.result`), plus split, split_source,
    presses, checkpoint, dataset, span, model_config, image_size, device, backend (what
    ran, e.g. ``"onnx/fp32"``), config, paper, definitions and (``config.baselines``)
    ``baselines``: the same metrics for an all-zero map ("zero") and the mean training
    label ("mean_gt"). With ``out_dir`` the files of the module docstring are written
    there. ``presses`` (dataset press ids) replaces ``config.split``: exactly those
    presses are scored (``train_presses``: the training presses, for the mean-label
    baseline).
    """
    config = config if config is not None else EvaluateConfig()
    model = as_model(checkpoint, config.device)
    out = Path(out_dir) if out_dir is not None else None
    with open_dataset(data) as ds, open_runtime(model, config.backend, config.precision) as rt:
        ds.require_presses()
        run = _Run(model, ds, evaluation_geometry(model, ds, config.resize), config, rt)
        if presses is None:
            selection = select_split(model, ds, config.split)
        else:
            selection = given_presses(ds, presses, train_presses)
        ends = evaluation_frames(model, ds, selection, config.max_frames)
        covered = coverage(ds, selection, model.span, ends.size, rest=bool(model.rest))
        _log_start(model, ds, selection, ends, covered, config, rt)
        base_maps = run.baseline_maps(selection, ends) if config.baselines else {}
        accs, col = run.loop(ends, base_maps, out, selection)
        metrics = _assemble(accs, model, ds, selection, ends, config, rt)
        metrics.update(col.breakdown.result())
        metrics.update(covered)
        if out is not None:
            metrics["files"] = {"metrics": METRICS_FILE, "predictions": PREDICTIONS_FILE}
            if config.plots:
                metrics["files"].update(_write_plots(out, ds, run.geometry, col, metrics))
            if config.report:
                metrics["files"]["report"] = REPORT_FILE
    if out is not None:
        write_metrics_json(metrics, out / METRICS_FILE)
        if config.report:
            write_report(evaluation_report(metrics, geometry=run.geometry), out)
        log.info("wrote %s", out)
    return metrics


def _log_start(model, ds, selection, ends, covered, config: EvaluateConfig, rt: Backend) -> None:
    log.info(
        "evaluating %s (%s) on %d frames of %d presses (%s split, %s) of %s: coverage %.1f%% "
        "of the split's %d valid frames (%.1f%% have a full window%s)",
        model.source,
        rt.describe(),
        ends.size,
        np.unique(ds.press_id[ends]).size,
        selection.name,
        selection.source,
        ds.path,
        100 * covered["coverage"],
        covered["valid_frames"],
        100 * covered["window_coverage"],
        f"; --max-frames {config.max_frames} took an even sample" if config.max_frames else "",
    )


@dataclass
class _Run:
    """One evaluation: the model, the open dataset and the geometry of the maps."""

    model: PressureModel
    ds: Dataset
    geometry: SensorGeometry  # the dataset's, at the model's image size
    config: EvaluateConfig
    runtime: Backend  # what runs the model

    def baseline_maps(self, selection: SplitSelection, ends: np.ndarray) -> dict[str, np.ndarray]:
        """The constant maps scored as baselines: all-zero and the mean training label."""
        ds, s = self.ds, self.geometry.image_size_px
        train_ends = selection_ends(ds, selection, self.model.span, True, bool(self.model.rest))
        source = train_ends if train_ends.size else ends
        return {
            "zero": np.zeros((s, s), np.float32),
            "mean_gt": mean_gt_map(ds, source, self.geometry, self.config.batch_size),
        }

    def loop(
        self,
        ends: np.ndarray,
        base_maps: dict[str, np.ndarray],
        out: Path | None,
        selection: SplitSelection,
    ) -> tuple[dict[str, MetricsAccumulator], _Collected]:
        """Predict, label and score ``ends`` batch by batch; append to predictions.h5."""
        ds, model = self.ds, self.model
        accs = {name: MetricsAccumulator(self.geometry) for name in ("model", *base_maps)}
        examples = _example_frames(ds, ends, EXAMPLE_PRESSES)
        trace = ds.press_id[examples[:TRACE_PRESSES]]
        col = _Collected(examples, trace, {}, [], Breakdown(self.geometry))
        reader = WindowReader(ds, model.span, self.geometry.image_size_px, bool(model.rest))
        with ExitStack() as stack:
            writer = None
            if out is not None:
                specs = _prediction_specs(self.geometry.image_size_px)
                writer = stack.enter_context(IncrementalH5(out / PREDICTIONS_FILE, specs))
                writer.file.attrs.update(_prediction_attrs(model, ds, self.geometry, selection))
            bar = stack.enter_context(
                tqdm(
                    total=ends.size, unit="frame", desc="evaluate", disable=not self.config.progress
                )
            )
            step = self.config.batch_size
            for i in range(0, ends.size, step):
                batch = ends[i : i + step]
                pred = _predict(self.runtime, model, ds, reader(batch), batch, step)
                gt = _labels(ds, batch, self.geometry)
                position = ds.position_mm[batch]
                fm = accs["model"].update(pred, gt, position)
                for name, base in base_maps.items():
                    accs[name].update(np.broadcast_to(base, gt.shape), gt, position)
                if writer is not None:
                    writer.append(
                        pred_kpa=pred,
                        gt_kpa=gt,
                        force_gt_n=fm.force_gt_n,
                        force_pred_n=fm.force_pred_n,
                        cop_gt_mm=fm.cop_gt_mm,
                        cop_pred_mm=fm.cop_pred_mm,
                        index=batch,
                    )
                _collect(col, ds, batch, pred, gt, fm)
                bar.update(batch.size)
        return accs, col


def _predict(
    runtime: Backend,
    model: PressureModel,
    ds: Dataset,
    windows: np.ndarray,
    batch: np.ndarray,
    batch_size: int,
) -> np.ndarray:
    pred = runtime.run_batch(windows, batch_size)
    finite = np.isfinite(pred).reshape(len(pred), -1).all(axis=1)
    if not finite.all():
        raise EvaluationError(
            f"{model.source}: the model predicted NaN/inf for frame {batch[np.argmin(finite)]} "
            f"of {ds.path}; the checkpoint's weights are probably broken"
        )
    return pred


def _assemble(accs, model, ds, selection, ends, config: EvaluateConfig, rt: Backend) -> dict:
    metrics = accs["model"].result()
    metrics.update(
        split=selection.name,
        split_source=selection.source,
        presses=int(np.unique(ds.press_id[ends]).size),
        checkpoint=str(model.source),
        dataset=str(ds.path),
        span=model.span,
        model_config=model.meta.model.to_dict(),  # frames (T), frame_stride, ...
        image_size=model.image_size,
        device=str(model.device),
        backend=rt.describe(),
        config=config.to_dict(),
        max_frames=config.max_frames,
        paper=dict(PAPER_METRICS),
        definitions=DEFINITIONS,
    )
    if len(accs) > 1:
        metrics["baselines"] = {name: acc.result() for name, acc in accs.items() if name != "model"}
        metrics["baselines_note"] = (
            "zero: an all-zero map; mean_gt: the mean label of the training presses' frames"
        )
    return metrics


def _prediction_attrs(
    model: PressureModel, ds: Dataset, geometry: SensorGeometry, selection: SplitSelection
) -> dict:
    return {
        "format": "beadsight-evaluation-predictions",
        "checkpoint": str(model.source),
        "dataset": str(ds.path),
        "split": selection.name,
        "geometry": geometry.to_json(),
        "rest_source": REST_FROM_DATASET if model.rest else REST_NONE,
        "units": json.dumps(
            {
                "pred_kpa": "kPa",
                "gt_kpa": "kPa",
                "force_gt_n": "N",
                "force_pred_n": "N",
                "cop_gt_mm": "mm (x, y)",
                "cop_pred_mm": "mm (x, y)",
                "index": "dataset frame index",
            }
        ),
        "cop_note": "cop_*_mm is NaN where that map has no positive pressure",
    }


def _write_plots(
    out: Path, ds: Dataset, geometry: SensorGeometry, col: _Collected, metrics: dict
) -> dict[str, str]:
    files = {}
    shown = [i for i in col.example_index.tolist() if i in col.examples]
    if shown:
        gt = np.stack([col.examples[i][0] for i in shown])
        pred = np.stack([col.examples[i][1] for i in shown])
        titles = [f"frame {i} ({ds.force_n[i]:.1f} N)" for i in shown]
        plot_examples(gt, pred, titles, geometry, out / EXAMPLES_PLOT)
        files["examples"] = EXAMPLES_PLOT
    plot_region_errors(
        metrics["region_mae_kpa"], metrics["region_frames"], geometry, out / REGION_PLOT
    )
    files["region_error"] = REGION_PLOT
    if col.trace_rows:
        rows = np.asarray(col.trace_rows, dtype=np.float64)
        traces = []
        for p in col.trace_presses.tolist():
            r = rows[rows[:, 1] == p]
            t = ds.timestamp_s[r[:, 0].astype(np.int64)]
            traces.append(ForceTrace(f"press {p}", t - t[0], r[:, 2], r[:, 3]))
        plot_force_traces(traces, out / FORCE_PLOT)
        files["force_traces"] = FORCE_PLOT
    return files | write_breakdown_files(out, col.breakdown, metrics)


def write_metrics_json(metrics: dict, path: str | Path) -> Path:
    """Write ``metrics`` as strict JSON (raises ValueError on NaN/inf), atomically."""
    return atomic_write_json(path, metrics, strict=True, mode=METRICS_FILE_MODE)
