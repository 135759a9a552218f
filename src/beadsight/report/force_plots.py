"""Force figures (PNG): predicted against true total force, and the error against force;
each with the caption a report shows under it.

Drawn like :mod:`beadsight.report.plots` (matplotlib's Agg canvas, written atomically).
``*_figure`` functions build the figure (tests read the data behind it from its artists);
``plot_*`` write it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from beadsight.report.plots import new_figure, save_figure

SCATTER_MAX_POINTS = 20_000  # frames drawn in the scatter, evenly spaced (all if fewer)


def force_scatter_figure(gt_n: np.ndarray, pred_n: np.ndarray) -> Figure:
    """Predicted (y) against true (x) total force, N, one dot per frame (at most
    :data:`SCATTER_MAX_POINTS`, evenly spaced), with the identity line y = x."""
    gt, pred = np.asarray(gt_n, np.float64), np.asarray(pred_n, np.float64)
    if gt.shape != pred.shape or gt.ndim != 1 or gt.size == 0:
        raise ValueError(f"need (N,) true and predicted forces, got {gt.shape}, {pred.shape}")
    if gt.size > SCATTER_MAX_POINTS:
        pick = np.linspace(0, gt.size - 1, SCATTER_MAX_POINTS).round().astype(np.int64)
        gt, pred = gt[pick], pred[pick]
    fig = new_figure(4.6, 4.2)
    ax = fig.subplots()
    fig.subplots_adjust(left=0.15, right=0.96, bottom=0.13, top=0.92)
    top = max(float(gt.max()), float(pred.max()), 1e-3) * 1.05
    low = min(float(pred.min()), 0.0)
    ax.plot([low, top], [low, top], color="grey", linestyle="--", linewidth=1, label="y = x")
    ax.scatter(gt, pred, s=6, alpha=0.5, color="tab:blue", edgecolors="none", label="frames")
    ax.set_xlim(low, top)
    ax.set_ylim(low, top)
    ax.set_aspect("equal")
    ax.set_xlabel("true total force (N)")
    ax.set_ylabel("predicted total force (N)")
    ax.set_title(f"Predicted against true force ({gt.size} frames)", fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    return fig


def plot_force_scatter(gt_n: np.ndarray, pred_n: np.ndarray, path: str | Path) -> Path:
    return save_figure(force_scatter_figure(gt_n, pred_n), path)


def force_error_figure(binned: Mapping) -> Figure:
    """The total-force error against true force: bars of ``error_pct`` per bin of
    ``edges_n`` (a :func:`beadsight.evaluation.breakdown.force_error_by_force` dict), each
    labelled with its frame count n; the mean absolute error (N) on a second axis."""
    edges = np.asarray(binned["edges_n"], np.float64)
    counts = list(binned["frames"])
    pct = np.array([np.nan if v is None else v for v in binned["error_pct"]], np.float64)
    abs_n = np.array([np.nan if v is None else v for v in binned["abs_error_n"]], np.float64)
    centres, widths = (edges[:-1] + edges[1:]) / 2, np.diff(edges)
    fig = new_figure(5.6, 3.6)
    ax = fig.subplots()
    fig.subplots_adjust(left=0.12, right=0.86, bottom=0.15, top=0.9)
    bars = ax.bar(centres, np.nan_to_num(pct), width=widths * 0.9, color="tab:orange")
    for bar, n, value in zip(bars, counts, pct, strict=True):
        text = f"n={n}" if np.isfinite(value) else "no frames"
        x = bar.get_x() + bar.get_width() / 2
        ax.annotate(text, (x, bar.get_height()), ha="center", va="bottom", fontsize=7)
    ax.set_xlabel("true total force (N)")
    ax.set_ylabel("total-force error (%)", color="tab:orange")
    ax.set_ylim(0, max(float(np.nanmax(pct)) if np.isfinite(pct).any() else 1.0, 1.0) * 1.2)
    twin = ax.twinx()
    twin.plot(centres, abs_n, "o-", color="black", markersize=4, label="mean |error| (N)")
    twin.set_ylabel("mean |F_pred - F_true| (N)")
    twin.set_ylim(bottom=0)
    twin.legend(fontsize=7, loc="upper right")
    ax.set_title("Force error by true force", fontsize=9)
    ax.grid(alpha=0.3, axis="y")
    return fig


def plot_force_error(binned: Mapping, path: str | Path) -> Path:
    return save_figure(force_error_figure(binned), path)


def force_scatter_caption() -> str:
    return (
        "Predicted against true total force (N, the integral of each pressure map), one dot "
        "per evaluated frame. Dots on the dashed line y = x are exact; dots above it are "
        "over-estimates, below it under-estimates. A slope below the line at high force means "
        "the model saturates; a cloud at x = 0 above the line is pressure predicted where none "
        "was applied."
    )


def force_error_caption() -> str:
    return (
        "The total-force error (%, bars: 100 * sum |F_pred - F_true| / sum F_true, the "
        "table's definition) in equal bins of the true force (N), over frames with a true "
        "force above 0; n above each bar is its number of frames (few frames: a noisy bar). "
        "The black line is the mean absolute error in N (right axis). Light presses have a "
        "high relative error even when the error in N is small."
    )
