"""Evaluation figures (PNG): example maps, the 4x4 region error map, force over time;
each with the caption a report shows under it.

Figures are drawn on matplotlib's Agg canvas directly (no pyplot, no global
backend state), so they work headless and in threads. Files are written with
:func:`beadsight.files.atomic_write`: a full disk raises
:class:`~beadsight.files.WriteError` and never leaves a truncated image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch, Rectangle

from beadsight.config import SensorGeometry
from beadsight.files import atomic_write

DPI = 110
PANEL_IN = 2.6  # side of one map panel, inches
PRESSURE_CMAP = "viridis"
ERROR_CMAP = "YlOrRd"  # pale yellow = low error, dark red = high: 0 is not black
NO_DATA_COLOUR = "0.85"  # cells without frames: light grey, hatched
NO_DATA_HATCH = "///"
MIN_COLOUR_RANGE_KPA = 1e-3  # colour scale floor, so all-zero maps still draw


def new_figure(width_in: float, height_in: float) -> Figure:
    # Fixed margins: matplotlib's constrained layout costs seconds per figure.
    fig = Figure(figsize=(width_in, height_in), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path) -> Path:
    return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=DPI))


def _extent_mm(geometry: SensorGeometry) -> list[float]:
    """imshow extent in printer mm: column 0 is printer +X, row 0 is printer +Y."""
    half = geometry.sensor_size_mm / 2
    return [half, -half, -half, half]


def plot_examples(
    gt_kpa: np.ndarray,
    pred_kpa: np.ndarray,
    titles: Sequence[str],
    geometry: SensorGeometry,
    path: str | Path,
) -> Path:
    """True (top row) vs predicted (bottom row) maps with one shared colour scale and bar.

    gt_kpa, pred_kpa: (K, H, W) kPa, K >= 1; titles: K strings. Returns ``path``.
    """
    gt_kpa, pred_kpa = np.asarray(gt_kpa), np.asarray(pred_kpa)
    k = len(gt_kpa)
    if k == 0 or gt_kpa.shape != pred_kpa.shape or len(titles) != k:
        raise ValueError(
            f"need K >= 1 matching maps and titles, got {gt_kpa.shape}, "
            f"{pred_kpa.shape}, {len(titles)} titles"
        )
    vmax = max(float(gt_kpa.max()), float(pred_kpa.max()), MIN_COLOUR_RANGE_KPA)
    fig = new_figure(PANEL_IN * k + 1.0, PANEL_IN * 2 + 0.4)
    axes = fig.subplots(2, k, squeeze=False)
    fig.subplots_adjust(
        left=0.6 / (PANEL_IN * k + 1.0), right=0.97, bottom=0.1, top=0.93, wspace=0.3, hspace=0.3
    )
    extent = _extent_mm(geometry)
    image = None
    for j in range(k):
        for i, (maps, name) in enumerate(((gt_kpa, "true"), (pred_kpa, "predicted"))):
            ax = axes[i, j]
            image = ax.imshow(maps[j], cmap=PRESSURE_CMAP, vmin=0.0, vmax=vmax, extent=extent)
            ax.set_title(f"{name}: {titles[j]}", fontsize=8)
            ax.tick_params(labelsize=7)
            if j == 0:
                ax.set_ylabel("y (mm)", fontsize=8)
            if i == 1:
                ax.set_xlabel("x (mm)", fontsize=8)
    fig.colorbar(image, ax=axes, shrink=0.8, fraction=0.3 / k, pad=0.02, label="pressure (kPa)")
    return save_figure(fig, path)


def region_values(region_mae_kpa: Sequence[Sequence[float | None]]) -> np.ma.MaskedArray:
    """The grid of per-region MAE (kPa) behind the region map: a masked float array whose
    cells without frames (None) are NaN and masked; every number, 0 included, is kept."""
    values = np.array(
        [[np.nan if v is None else float(v) for v in row] for row in region_mae_kpa], float
    )
    return np.ma.masked_invalid(values)


def _cell_text(value: float) -> str:
    """A cell's MAE with 3 significant digits, so a small error never prints as 0.00."""
    return "0" if value == 0 else f"{value:.3g}"


def region_error_figure(
    region_mae_kpa: Sequence[Sequence[float | None]],
    region_frames: Sequence[Sequence[int]],
    geometry: SensorGeometry,
) -> Figure:
    """The grid of per-region MAE (kPa), annotated with values and frame counts.

    Cells with frames take their colour from the scale (0 kPa pale, the worst cell dark
    red); cells without frames are masked (NaN), drawn hatched grey and named in the legend.
    Orientation matches the pressure maps.
    """
    values = region_values(region_mae_kpa)
    counts = np.asarray(region_frames, dtype=np.int64)
    grid = values.shape[0]
    fig = new_figure(4.8, 4.3)
    ax = fig.subplots()
    fig.subplots_adjust(left=0.14, right=0.95, bottom=0.2, top=0.92)
    vmax = max(float(values.max()) if values.count() else 0.0, MIN_COLOUR_RANGE_KPA)
    extent = _extent_mm(geometry)
    cmap = matplotlib.colormaps[ERROR_CMAP].with_extremes(bad=NO_DATA_COLOUR)
    image = ax.imshow(values, cmap=cmap, vmin=0.0, vmax=vmax, extent=extent)
    cell_mm = geometry.sensor_size_mm / grid
    half = geometry.sensor_size_mm / 2
    for i in range(grid):
        for j in range(grid):
            x = half - (j + 0.5) * cell_mm
            y = half - (i + 0.5) * cell_mm
            if values.mask[i, j]:
                corner = (x - cell_mm / 2, y - cell_mm / 2)
                ax.add_patch(
                    Rectangle(
                        corner,
                        cell_mm,
                        cell_mm,
                        fill=False,
                        hatch=NO_DATA_HATCH,
                        edgecolor="0.55",
                        linewidth=0,
                    )
                )
                text, colour = "no frames", "black"
            else:
                text = _cell_text(float(values[i, j]))
                colour = "white" if values[i, j] > 0.6 * vmax else "black"
            ax.text(
                x,
                y,
                f"{text}\nn={counts[i, j]}",
                ha="center",
                va="center",
                fontsize=7,
                color=colour,
            )
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"MAE by press location ({cell_mm:g} mm cells)", fontsize=9)
    no_data = Patch(
        facecolor=NO_DATA_COLOUR,
        hatch=NO_DATA_HATCH,
        edgecolor="0.55",
        label="no frames (no press here): not 0",
    )
    fig.legend(handles=[no_data], loc="lower left", fontsize=7, frameon=False)
    fig.colorbar(image, ax=ax, label="MAE (kPa)")
    return fig


def plot_region_errors(
    region_mae_kpa: Sequence[Sequence[float | None]],
    region_frames: Sequence[Sequence[int]],
    geometry: SensorGeometry,
    path: str | Path,
) -> Path:
    """Write :func:`region_error_figure` to ``path``."""
    return save_figure(region_error_figure(region_mae_kpa, region_frames, geometry), path)


@dataclass(frozen=True)
class ForceTrace:
    """One press: time (s from its first frame), true and predicted total force (N)."""

    label: str
    time_s: np.ndarray
    force_gt_n: np.ndarray
    force_pred_n: np.ndarray


def plot_force_traces(traces: Sequence[ForceTrace], path: str | Path) -> Path:
    """Total force over time for a few presses: ground truth vs prediction."""
    if not traces:
        raise ValueError("need at least one force trace")
    fig = new_figure(3.2 * len(traces) + 0.75, 3.0)
    axes = fig.subplots(1, len(traces), squeeze=False)[0]
    fig.subplots_adjust(
        left=0.75 / (3.2 * len(traces) + 0.75), right=0.98, bottom=0.17, top=0.9, wspace=0.25
    )
    for ax, trace in zip(axes, traces, strict=True):
        ax.plot(trace.time_s, trace.force_gt_n, color="black", label="true")
        ax.plot(
            trace.time_s, trace.force_pred_n, color="tab:red", linestyle="--", label="predicted"
        )
        ax.set_title(trace.label, fontsize=9)
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("total force (N)")
    axes[0].legend(fontsize=8)
    return save_figure(fig, path)


# --- captions -----------------------------------------------------------------------
# What each figure shows and how to read it, for the reports (beadsight.report.page).
MAP_AXES = (
    "Maps are drawn as the camera sees the sensor: x (mm, printer X) grows to the left, "
    "y (mm, printer Y) grows upwards, 0 at the sensor centre."
)


def examples_caption() -> str:
    return (
        "True (top row) and predicted (bottom row) pressure maps at the frame of peak force of "
        "a few presses spread over the evaluated data; the title gives the frame index and the "
        f"true total force. {MAP_AXES} Colour: pressure in kPa ({PRESSURE_CMAP}: dark purple "
        "0 kPa, yellow the maximum), one scale shared by all panels (bar on the right)."
    )


def region_error_caption(grid: int, cell_mm: float) -> str:
    return (
        f"Pressure MAE (kPa) by where the press was: the field of view cut into {grid} x {grid} "
        f"cells of {cell_mm:g} mm, each frame counted in the cell of its press's commanded "
        f"position (all frames of the press). Colour: MAE in kPa (pale yellow 0, dark red "
        "the worst cell); each cell prints its MAE and n, its number of frames. Hatched grey "
        "cells had no presses: no data, not an error of 0 (the legend says so). "
        f"{MAP_AXES}"
    )


def force_traces_caption() -> str:
    return (
        "Total force (N, the integral of the pressure map) over time for a few presses: the "
        "ground truth (black, solid) and the model's prediction (red, dashed). Time in s from "
        "the press's first evaluated frame; where frames were subsampled (--max-frames) the "
        "lines join the evaluated frames."
    )


# --- calibration --------------------------------------------------------------------
@dataclass(frozen=True)
class CurvePoint:
    """One model of a calibration, scored on the held-out presses."""

    label: str  # e.g. "zero-shot"
    presses: int  # presses its weights were trained on (0: none of this sensor's)
    force_error_pct: float | None


def plot_learning_curve(
    points: Sequence[CurvePoint],
    val_time_s: np.ndarray,
    val_mae_kpa: np.ndarray,
    kept: int | None,
    paper_force_error_pct: float,
    path: str | Path,
) -> Path:
    """Left: held-out force error against the presses used; right: the early-stopping
    presses' MAE over the fine-tuning (time in s), the kept checkpoint (index ``kept``)
    circled."""
    fig = new_figure(8.0, 3.2)
    left, right = fig.subplots(1, 2)
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.16, top=0.88, wspace=0.3)
    for point in points:
        if point.force_error_pct is not None:
            left.plot(point.presses, point.force_error_pct, "o", label=point.label)
    left.axhline(paper_force_error_pct, color="grey", linestyle=":", label="paper")
    left.set_xlabel("presses of this sensor trained on")
    left.set_ylabel("force error on held-out presses (%)")
    left.set_ylim(bottom=0)
    left.legend(fontsize=7)
    left.grid(alpha=0.3)
    if len(val_time_s):
        right.plot(val_time_s, val_mae_kpa, "-o", markersize=3, color="tab:blue")
        if kept is not None:
            right.plot(val_time_s[kept], val_mae_kpa[kept], "o", mfc="none", ms=10, color="tab:red")
    else:
        right.text(0.5, 0.5, "no fine-tuning", ha="center", va="center", transform=right.transAxes)
    right.set_xlabel("fine-tuning time (s)")
    right.set_ylabel("MAE on early-stopping presses (kPa)")
    right.grid(alpha=0.3)
    return save_figure(fig, path)


def learning_curve_caption() -> str:
    return (
        "Left: total-force error (%) on this sensor's held-out test presses against the number "
        "of its presses the model was trained on: the base model as it came (zero-shot) and "
        "after the zero-press alignment (both 0 presses), and the calibrated model; the dotted "
        "line is the paper's 11.9 %. These are the models of this one run, not a curve over "
        "press counts: benchmarks/calibration_curve.py measures that. Right: the validation "
        "MAE (kPa) on the early-stopping presses during fine-tuning against its wall-clock "
        "time; the red circle marks the checkpoint kept (lowest validation loss)."
    )
