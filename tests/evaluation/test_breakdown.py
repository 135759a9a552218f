"""The evaluation broken down (issue 26): predicted against true force, the error against
force, the per-press table, the learning curve of the checkpoint's run, and a region map
whose empty cells are masked, not drawn as an error of 0. Each checks the file and the data
behind it against what predictions.h5 holds, recomputed here."""

from __future__ import annotations

import csv
import json

import cv2
import h5py
import matplotlib
import numpy as np
import pytest
import torch
from helpers.synthetic_presses import write_synthetic_dataset

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.dataset import open_dataset
from beadsight.evaluation.breakdown import PRESS_COLUMNS, force_error_by_force
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.metrics import compute_metrics
from beadsight.report.force_plots import force_error_figure, force_scatter_figure
from beadsight.report.plots import ERROR_CMAP, NO_DATA_COLOUR, region_error_figure
from beadsight.report.training import TRAINING_LOG, read_training_curve, training_curve_figure
from beadsight.train.run import METRICS_FILE, RunFolder

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # a shared 2-core machine


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """evaluate() of an untrained tiny model, saved in a run folder with a training log
    written by the trainer's own writer."""
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(frames=15, width=8),
        geometry=SensorGeometry(image_size_px=64),
        pixel_mean=[120.0, 120.0, 120.0],
        pixel_std=[40.0, 40.0, 40.0],
        output_scale_kpa=10.0,
    )
    root = tmp_path_factory.mktemp("breakdown")
    data = write_synthetic_dataset(root / "data.h5", 5, 24, 64, 0, 30.0)  # 5 presses, 106 frames
    run = RunFolder(root / "run")
    run.path.mkdir()
    checkpoint = PressureModel.create(meta).save(run.best)
    for step, loss in ((10, 0.9), (20, 0.5), (30, 0.4)):  # the trainer's own writer
        run.log(event="train", step=step, train_loss=loss, time_s=step / 10)
    run.log(event="val", step=15, val_loss=0.7, val_mae_kpa=1.5, train_loss=0.8)
    run.log(event="val", step=30, val_loss=0.45, val_mae_kpa=1.1, train_loss=0.4)
    out = root / "eval"
    metrics = evaluate(checkpoint, data, EvaluateConfig(split="all", progress=False), out)
    return metrics, out, data


def _predictions(out):
    with h5py.File(out / "predictions.h5", "r") as f:
        return {k: f[k][()] for k in f}


def test_the_per_press_table_is_each_press_recomputed_worst_first(evaluated):
    metrics, out, data = evaluated
    p = _predictions(out)
    with h5py.File(out / "predictions.h5", "r") as f:
        geometry = SensorGeometry.from_dict(json.loads(f.attrs["geometry"]))
    rows = metrics["per_press"]
    with open_dataset(data) as ds:
        press_of = ds.press_id[p["index"]]
        positions = ds.position_mm[p["index"]]
    assert sorted(r["press"] for r in rows) == sorted(set(press_of.tolist())) and len(rows) == 5
    for row in rows:
        mine = press_of == row["press"]
        expected = compute_metrics(
            p["pred_kpa"][mine], p["gt_kpa"][mine], positions[mine], geometry
        )
        assert row["frames"] == expected["frames"] == int(mine.sum())
        for key in ("force_error_pct", "cop_error_mm", "iou", "mae_kpa"):
            assert row[key] == pytest.approx(expected[key], rel=1e-9), key
        assert row["peak_force_n"] == pytest.approx(p["force_gt_n"][mine].max())
        assert [row["x_mm"], row["y_mm"]] == pytest.approx(positions[mine].mean(axis=0).tolist())
    errors = [r["force_error_pct"] for r in rows]
    assert errors == sorted(errors, reverse=True)  # worst first
    # the same rows, in the same order, in presses.csv and in metrics.json
    with open(out / "presses.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert tuple(table[0]) == PRESS_COLUMNS
    assert [int(r["press"]) for r in table] == [r["press"] for r in rows]
    assert [float(r["force_error_pct"]) for r in table] == pytest.approx(errors)
    assert json.loads((out / "metrics.json").read_text())["per_press"] == rows
    assert metrics["files"]["presses"] == "presses.csv"


def test_the_scatter_draws_each_frames_true_and_predicted_force(evaluated):
    metrics, out, _ = evaluated
    p = _predictions(out)
    image = cv2.imread(str(out / "force_scatter.png"))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 300
    assert metrics["files"]["force_scatter"] == "force_scatter.png"
    ax = force_scatter_figure(p["force_gt_n"], p["force_pred_n"]).axes[0]
    points = ax.collections[0].get_offsets()
    assert np.array_equal(points, np.column_stack([p["force_gt_n"], p["force_pred_n"]]))
    identity = ax.lines[0].get_xydata()
    assert identity[0, 0] == identity[0, 1] and identity[1, 0] == identity[1, 1]
    assert identity[1, 0] >= max(p["force_gt_n"].max(), p["force_pred_n"].max())


def test_the_error_against_force_is_binned_from_the_frames_forces(evaluated):
    metrics, out, _ = evaluated
    p = _predictions(out)
    binned = metrics["force_error_by_force"]
    assert cv2.imread(str(out / "force_error.png")) is not None
    gt, pred = p["force_gt_n"], p["force_pred_n"]
    loaded = gt > 0
    assert sum(binned["frames"]) == int(loaded.sum()) == metrics["force_frames"]
    edges = binned["edges_n"]
    assert edges[0] == 0 and edges[-1] == pytest.approx(gt.max())
    for b, n in enumerate(binned["frames"]):
        last = b == len(binned["frames"]) - 1
        inside = loaded & (gt >= edges[b]) & ((gt <= edges[b + 1]) if last else (gt < edges[b + 1]))
        assert n == int(inside.sum())
        if n:
            g, q = gt[inside], pred[inside]
            assert binned["error_pct"][b] == pytest.approx(100 * np.abs(q - g).sum() / g.sum())
            assert binned["abs_error_n"][b] == pytest.approx(np.abs(q - g).mean())
        else:
            assert binned["error_pct"][b] is None
    # the figure's bars are those numbers, each labelled with its count
    ax = force_error_figure(binned).axes[0]
    heights = [bar.get_height() for bar in ax.patches]
    assert heights == pytest.approx([v or 0.0 for v in binned["error_pct"]])
    labels = [t.get_text() for t in ax.texts]
    assert labels == [f"n={n}" if n else "no frames" for n in binned["frames"]]


def test_force_error_by_force_by_hand():
    binned = force_error_by_force(np.array([0.0, 1.0, 2.0, 4.0]), np.array([5, 2, 1, 4.0]), 2)
    assert binned["edges_n"] == [0.0, 2.0, 4.0]
    assert binned["frames"] == [1, 2]  # the 0 N frame is not counted, as in the table
    assert binned["error_pct"] == pytest.approx([100.0, 100 * 1 / 6])
    assert binned["abs_error_n"] == pytest.approx([1.0, 0.5])
    assert binned["bias_n"] == pytest.approx([1.0, -0.5])


def test_the_learning_curve_is_the_runs_log(evaluated):
    metrics, out, _ = evaluated
    assert TRAINING_LOG == METRICS_FILE  # the name train writes is the name reports read
    assert metrics["files"]["training_curve"] == "training_curve.png"
    assert cv2.imread(str(out / "training_curve.png")) is not None
    curve = read_training_curve(out.parent / "run" / TRAINING_LOG)
    assert curve.train_step.tolist() == [10, 20, 30] and curve.train_loss.tolist() == [
        0.9,
        0.5,
        0.4,
    ]
    assert curve.val_step.tolist() == [15, 30] and curve.val_mae_kpa.tolist() == [1.5, 1.1]
    left, right = training_curve_figure(curve).axes
    assert left.lines[0].get_xydata().tolist() == [[10, 0.9], [20, 0.5], [30, 0.4]]
    assert left.lines[1].get_xydata().tolist() == [[15, 0.7], [30, 0.45]]
    assert right.lines[0].get_xydata().tolist() == [[15, 1.5], [30, 1.1]]
    assert right.lines[1].get_xydata().tolist() == [[30, 1.1]]  # the lowest, circled


def test_no_learning_curve_without_a_log_of_two_points(tmp_path, tiny_model, make_dataset):
    checkpoint = tiny_model.save(tmp_path / "alone" / "model.pt")
    (tmp_path / "alone" / TRAINING_LOG).write_text('{"event": "val", "step": 5}\nnot json\n')
    data = make_dataset(presses=3)
    settings = EvaluateConfig(split="all", max_frames=24, progress=False)  # any frames do
    metrics = evaluate(checkpoint, data, settings, tmp_path / "e")
    assert "training_curve" not in metrics["files"]
    assert not (tmp_path / "e" / "training_curve.png").exists()
    assert {"force_scatter", "force_error", "presses"} <= set(metrics["files"])


def test_region_cells_without_frames_are_masked_and_zero_is_a_colour():
    geometry = SensorGeometry(image_size_px=64)
    mae = [[None, 0.0, 0.004, 1.0], [None] * 4, [0.5, None, None, None], [None] * 4]
    frames = [[0, 3, 4, 5], [0] * 4, [6, 0, 0, 0], [0] * 4]
    fig = region_error_figure(mae, frames, geometry)
    ax = fig.axes[0]
    drawn = ax.images[0].get_array()
    empty = np.array([[v is None for v in row] for row in mae])
    assert np.array_equal(np.ma.getmaskarray(drawn), empty)
    assert np.isnan(drawn.data[empty]).all()  # no data is NaN, never 0
    assert drawn[0, 1] == 0.0 and not np.ma.is_masked(drawn[0, 1])
    # 0 kPa takes the scale's own colour (pale), masked cells the grey "bad" colour
    image = ax.images[0]
    rgba = image.to_rgba(drawn)
    assert np.allclose(rgba[0, 1], matplotlib.colormaps[ERROR_CMAP](0.0))
    assert np.allclose(rgba[0, 0], matplotlib.colors.to_rgba(NO_DATA_COLOUR))
    assert min(rgba[0, 1][:3]) > 0.5  # light, not black
    hatched = [p for p in ax.patches if p.get_hatch()]
    assert len(hatched) == int(empty.sum())
    texts = [t.get_text() for t in ax.texts]
    assert "0\nn=3" in texts and "0.004\nn=4" in texts  # a small error is not printed 0.00
    assert texts.count("no frames\nn=0") == int(empty.sum())
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend and "no frames" in legend[0]
