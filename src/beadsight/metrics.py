"""Pressure-map metrics of the BeadSight paper, accumulated in a streaming fashion.

Definitions (reference-facts section 8, the intended ones, not the reference
code's defects):

* **pressure MAE** (kPa): mean over frames of the mean ``|pred - gt|`` over all pixels.
* **total-force error** (%): ``mean |F_pred - F_gt| / mean F_gt`` over frames whose
  ground-truth force is non-zero; ``F`` is the integral of a map
  (:func:`beadsight.geometry.total_force_n`) for both prediction and ground truth.
* **centre of pressure** (mm): distance between the pressure-weighted centroids of
  prediction and ground truth, on frames with ``F_gt >= 2 N``. A prediction with no
  positive pressure has no centroid; it is *measured from the sensor centre*
  (its CoP is taken to be (0, 0) mm), a finite penalty equal to the distance of the
  true CoP from the centre. Such frames are counted in ``cop_empty_prediction_frames``.
* **contact IoU** (0..1): Otsu threshold (:func:`beadsight.geometry.otsu_masks`) on the predicted map
  vs the true contact disk, on frames with ``F_gt >= 2 N`` (every such frame, not a
  subsample). An empty or constant prediction has an empty mask: IoU 0.
  The paper compares with ``gt > 0`` on hard-edged disk labels. Our labels are
  anti-aliased (rim pixels carry their partial coverage), so ``gt > 0`` would add
  a half-pixel ring no thresholded map can match (a perfect prediction would score
  ~0.97 at 256 px, ~0.91 at 64 px). The true contact mask is therefore the ground
  truth binarised by the same Otsu rule (:func:`gt_contact_masks`): for a
  hard-edged label that is exactly ``gt > 0``; for an anti-aliased one it is the
  finger's disk, and a perfect prediction scores 1.
* **region MAE** (kPa): the per-frame MAE of every evaluated frame, grouped by the
  commanded position of its press on a 4 x 4 grid over the sensor's field of view
  (cells of ``sensor_size_mm / 4`` = 10.25 mm); the worst cell is reported. All
  frames of a press count (approach, contact, release), as in the overall MAE, so
  the two are comparable (paper: 0.79 kPa overall, 1.05 kPa worst cell). Cell ``[i][j]`` is
  image row-band ``i`` (top = printer +Y) and column-band ``j`` (left = printer +X),
  the same orientation as the pressure maps. Cells without frames are ``None``.

Every value :meth:`MetricsAccumulator.result` returns is a finite float, an int,
or ``None`` (never NaN), so it serialises to strict JSON.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.geometry import centre_of_pressure_mm, mm_to_px, otsu_masks, total_force_n

REGION_GRID = 4  # the paper's 4 x 4 grid of press-location cells (10.25 mm at 41 mm)
PAPER_METRIC_KEYS = ("mae_kpa", "force_error_pct", "cop_error_mm", "iou", "worst_region_mae_kpa")
MIN_SHAPE_FORCE_N = 2.0  # CoP and IoU only on frames with at least this true force (paper)


def gt_contact_masks(gt_kpa: np.ndarray) -> np.ndarray:
    """True contact of (B, H, W) ground-truth maps -> (B, H, W) bool.

    The Otsu foreground of each label: identical to ``gt > 0`` for hard-edged
    labels (two values), and the finger's disk (pixels about half covered or more)
    for anti-aliased ones. All-zero labels give empty masks.
    """
    return otsu_masks(gt_kpa)


def contact_iou(pred_mask: np.ndarray, gt_mask: np.ndarray) -> np.ndarray:
    """Intersection over union of (B, H, W) bool masks -> (B,) float64 in 0..1.

    Two empty masks agree perfectly (1.0); this never yields NaN.
    """
    inter = (pred_mask & gt_mask).sum(axis=(-2, -1))
    union = (pred_mask | gt_mask).sum(axis=(-2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


# --- regions ------------------------------------------------------------------------
def region_cells(
    position_mm: np.ndarray, geometry: SensorGeometry, grid: int = REGION_GRID
) -> np.ndarray:
    """Grid cell of each press position: (B, 2) mm (x, y) -> (B, 2) int64 (row, col).

    The grid divides the field of view into ``grid`` x ``grid`` equal cells in image
    orientation (row 0 = top = printer +Y, col 0 = left = printer +X). Positions on
    a boundary go to the higher cell; positions outside the field to the edge cell.
    """
    rc = mm_to_px(np.asarray(position_mm, np.float64).reshape(-1, 2), geometry)
    cell_px = geometry.image_size_px / grid
    return np.clip(np.floor(rc / cell_px), 0, grid - 1).astype(np.int64)


# --- per-frame values ---------------------------------------------------------------
@dataclass(frozen=True)
class FrameMetrics:
    """Per-frame quantities of a batch of B frames (float64 unless noted).

    mae_kpa (B,); force_pred_n, force_gt_n (B,) N (map integrals); cop_pred_mm,
    cop_gt_mm (B, 2) mm, NaN where that map has no positive pressure;
    cop_error_mm (B,) mm, NaN where ``F_gt < MIN_SHAPE_FORCE_N`` (empty predictions
    measured from the sensor centre); iou (B,) 0..1, NaN where ``F_gt <
    MIN_SHAPE_FORCE_N``; cell (B, 2) int64 region (row, col) of the true position.
    """

    mae_kpa: np.ndarray
    force_pred_n: np.ndarray
    force_gt_n: np.ndarray
    cop_pred_mm: np.ndarray
    cop_gt_mm: np.ndarray
    cop_error_mm: np.ndarray
    iou: np.ndarray
    cell: np.ndarray

    @property
    def force_mask(self) -> np.ndarray:
        """(B,) bool: frames that count for the total-force error."""
        return self.force_gt_n > 0

    @property
    def shape_mask(self) -> np.ndarray:
        """(B,) bool: frames that count for CoP and IoU."""
        return self.force_gt_n >= MIN_SHAPE_FORCE_N


def frame_metrics(
    pred_kpa: np.ndarray,
    gt_kpa: np.ndarray,
    position_mm: np.ndarray,
    geometry: SensorGeometry,
    grid: int = REGION_GRID,
) -> FrameMetrics:
    """Per-frame metrics of a batch.

    pred_kpa, gt_kpa: (B, H, W) float kPa; position_mm: (B, 2) true press position,
    mm. geometry: the sensor geometry of the maps (field of view, for mm units).
    Raises ValueError on shape mismatch or non-finite predictions.
    """
    pred = np.asarray(pred_kpa)
    gt = np.asarray(gt_kpa)
    if pred.ndim != 3 or pred.shape != gt.shape:
        raise ValueError(
            f"pred_kpa {pred.shape} and gt_kpa {gt.shape} must both be (B, H, W) of one shape"
        )
    if not np.isfinite(pred).all():
        bad = int(np.flatnonzero(~np.isfinite(pred).reshape(len(pred), -1).all(axis=1))[0])
        raise ValueError(f"pred_kpa: non-finite values (NaN/inf) in frame {bad} of the batch")
    g = geometry.with_image_size(pred.shape[-1])
    mae = np.abs(pred.astype(np.float64) - gt).mean(axis=(1, 2))
    force_pred = np.asarray(total_force_n(pred.astype(np.float64), g))
    force_gt = np.asarray(total_force_n(gt.astype(np.float64), g))
    cop_pred = centre_of_pressure_mm(pred, g)
    cop_gt = centre_of_pressure_mm(gt, g)
    shape = force_gt >= MIN_SHAPE_FORCE_N
    cop_pred_or_centre = np.where(np.isnan(cop_pred), 0.0, cop_pred)  # empty -> sensor centre
    cop_err = np.full(len(pred), np.nan)
    cop_err[shape] = np.linalg.norm(cop_pred_or_centre[shape] - cop_gt[shape], axis=1)
    iou = np.full(len(pred), np.nan)
    if shape.any():
        iou[shape] = contact_iou(otsu_masks(pred[shape]), gt_contact_masks(gt[shape]))
    return FrameMetrics(
        mae_kpa=mae,
        force_pred_n=force_pred,
        force_gt_n=force_gt,
        cop_pred_mm=cop_pred,
        cop_gt_mm=cop_gt,
        cop_error_mm=cop_err,
        iou=iou,
        cell=region_cells(position_mm, geometry, grid),
    )


# --- streaming accumulation ---------------------------------------------------------
def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


class MetricsAccumulator:
    """Sums per-frame metrics batch by batch; memory does not grow with the frame count.

    Usage::

        acc = MetricsAccumulator(geometry)
        for pred, gt, pos in batches:
            acc.update(pred, gt, pos)
        metrics = acc.result()
    """

    def __init__(self, geometry: SensorGeometry, grid: int = REGION_GRID):
        self.geometry = geometry
        self.grid = grid
        self.frames = 0
        self.mae_sum = 0.0
        self.force_frames = 0
        self.force_abs_error_sum = 0.0
        self.force_gt_sum = 0.0
        self.shape_frames = 0
        self.cop_sum = 0.0
        self.cop_empty = 0
        self.iou_sum = 0.0
        self.region_sum = np.zeros((grid, grid))
        self.region_count = np.zeros((grid, grid), dtype=np.int64)

    def update(
        self, pred_kpa: np.ndarray, gt_kpa: np.ndarray, position_mm: np.ndarray
    ) -> FrameMetrics:
        """Add a batch: pred_kpa, gt_kpa (B, H, W) kPa; position_mm (B, 2). Returns its per-frame values."""
        fm = frame_metrics(pred_kpa, gt_kpa, position_mm, self.geometry, self.grid)
        self.add(fm)
        return fm

    def add(self, fm: FrameMetrics) -> None:
        """Add precomputed per-frame values."""
        self.frames += len(fm.mae_kpa)
        self.mae_sum += float(fm.mae_kpa.sum())
        force = fm.force_mask
        self.force_frames += int(force.sum())
        self.force_abs_error_sum += float(np.abs(fm.force_pred_n - fm.force_gt_n)[force].sum())
        self.force_gt_sum += float(fm.force_gt_n[force].sum())
        shape = fm.shape_mask
        self.shape_frames += int(shape.sum())
        self.cop_sum += float(fm.cop_error_mm[shape].sum())
        self.cop_empty += int(np.isnan(fm.cop_pred_mm[shape, 0]).sum())
        self.iou_sum += float(fm.iou[shape].sum())
        np.add.at(self.region_sum, (fm.cell[:, 0], fm.cell[:, 1]), fm.mae_kpa)
        np.add.at(self.region_count, (fm.cell[:, 0], fm.cell[:, 1]), 1)

    def result(self) -> dict:
        """The metrics as a JSON-ready dict (floats, ints, None; no NaN).

        Keys: mae_kpa, force_error_pct, cop_error_mm, iou, region_mae_kpa (grid x grid
        nested list, None for empty cells), region_frames, worst_region_mae_kpa,
        worst_region_cell ([row, col]), frames, force_frames, cop_frames, iou_frames,
        cop_empty_prediction_frames, region_frames_total, force_gt_mean_n.
        A metric with no eligible frames is None.
        """

        def mean(total: float, count: int) -> float | None:
            return _finite_or_none(total / count) if count else None

        region = np.full((self.grid, self.grid), np.nan)
        np.divide(self.region_sum, self.region_count, out=region, where=self.region_count > 0)
        if self.region_count.any():
            worst = np.unravel_index(np.nanargmax(region), region.shape)
            worst_value, worst_cell = float(region[worst]), [int(worst[0]), int(worst[1])]
        else:
            worst_value, worst_cell = None, None
        force_pct = (
            _finite_or_none(100.0 * self.force_abs_error_sum / self.force_gt_sum)
            if self.force_frames and self.force_gt_sum > 0
            else None
        )
        return {
            "mae_kpa": mean(self.mae_sum, self.frames),
            "force_error_pct": force_pct,
            "cop_error_mm": mean(self.cop_sum, self.shape_frames),
            "iou": mean(self.iou_sum, self.shape_frames),
            "region_mae_kpa": [[_finite_or_none(v) for v in row] for row in region.tolist()],
            "region_frames": self.region_count.tolist(),
            "worst_region_mae_kpa": worst_value,
            "worst_region_cell": worst_cell,
            "frames": self.frames,
            "force_frames": self.force_frames,
            "cop_frames": self.shape_frames,
            "iou_frames": self.shape_frames,
            "cop_empty_prediction_frames": self.cop_empty,
            "region_frames_total": int(self.region_count.sum()),
            "force_gt_mean_n": mean(self.force_gt_sum, self.force_frames),
        }


def compute_metrics(
    pred_kpa: np.ndarray, gt_kpa: np.ndarray, position_mm: np.ndarray, geometry: SensorGeometry
) -> dict:
    """All metrics of one in-memory batch (see :meth:`MetricsAccumulator.result`)."""
    acc = MetricsAccumulator(geometry)
    acc.update(pred_kpa, gt_kpa, position_mm)
    return acc.result()
