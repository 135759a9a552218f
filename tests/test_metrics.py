"""Metric definitions against hand-computed values (64x64 maps, 0.640625 mm per pixel)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from beadsight.config import SensorGeometry
from beadsight.geometry import disk_maps, otsu_masks, otsu_thresholds
from beadsight.metrics import (
    MIN_SHAPE_FORCE_N,
    MetricsAccumulator,
    compute_metrics,
    contact_iou,
    region_cells,
)
from beadsight.report.paper import PAPER_METRICS, format_metrics_table

G = SensorGeometry(image_size_px=64)
MM_PER_PX = 41 / 64  # 0.640625


def disk(force_n: float, dx_px: int = 0, dy_px: int = 0) -> np.ndarray:
    """(1, 64, 64) disk whose centre sits on a pixel corner ``dx_px``/``dy_px`` px from the
    image centre (printer +X/+Y), so it is symmetric on the pixel grid."""
    xy = np.array([[dx_px * MM_PER_PX, dy_px * MM_PER_PX]])
    return disk_maps(np.array([force_n]), xy, G)


def strict_json(metrics: dict) -> dict:
    def refuse(token):
        raise AssertionError(f"non-finite JSON constant {token}")

    return json.loads(json.dumps(metrics, allow_nan=False), parse_constant=refuse)


def test_paper_metrics_constant():
    assert PAPER_METRICS == {
        "mae_kpa": 0.79,
        "force_error_pct": 11.9,
        "cop_error_mm": 1.18,
        "iou": 0.81,
        "worst_region_mae_kpa": 1.05,
    }


def test_perfect_prediction():
    gt = np.concatenate([disk(10.0), disk(6.0, 5, -7)])
    pos = np.array([[0.0, 0.0], [5 * MM_PER_PX, -7 * MM_PER_PX]])
    m = compute_metrics(gt.copy(), gt, pos, G)
    assert m["mae_kpa"] == 0.0
    assert m["force_error_pct"] == 0.0
    assert m["cop_error_mm"] == pytest.approx(0.0, abs=1e-12)
    assert m["iou"] == 1.0
    assert m["worst_region_mae_kpa"] == 0.0
    assert m["frames"] == m["force_frames"] == m["cop_frames"] == m["iou_frames"] == 2


def test_shifted_disk_cop_error_is_the_shift():
    gt = disk(10.0)
    pred = np.roll(gt, (4, 3), axis=(1, 2))  # 4 px down, 3 px right: 5 px
    m = compute_metrics(pred, gt, np.zeros((1, 2)), G)
    assert m["cop_error_mm"] == pytest.approx(5 * MM_PER_PX, abs=1e-9)  # 3.203125 mm
    assert m["force_error_pct"] == pytest.approx(0.0, abs=1e-9)
    assert 0.0 < m["iou"] < 1.0


def test_scaled_map_force_error_and_mae():
    gt = disk(8.0, 2, 2)
    m = compute_metrics(1.5 * gt, gt, np.zeros((1, 2)), G)
    assert m["force_error_pct"] == pytest.approx(50.0)
    assert m["mae_kpa"] == pytest.approx(0.5 * float(gt.mean(dtype=np.float64)), rel=1e-6)
    assert m["iou"] == 1.0  # Otsu does not care about the scale
    assert m["cop_error_mm"] == pytest.approx(0.0, abs=1e-9)


def test_empty_prediction_is_finite():
    gt = disk(10.0, 3, -4)  # true CoP 5 px from the centre
    m = compute_metrics(np.zeros_like(gt), gt, np.array([[3 * MM_PER_PX, -4 * MM_PER_PX]]), G)
    assert m["cop_error_mm"] == pytest.approx(5 * MM_PER_PX, abs=1e-9)  # measured from centre
    assert m["cop_empty_prediction_frames"] == 1
    assert m["iou"] == 0.0
    assert m["force_error_pct"] == pytest.approx(100.0)
    assert m["mae_kpa"] == pytest.approx(float(gt.mean(dtype=np.float64)), rel=1e-6)
    strict_json(m)


def test_frame_eligibility():
    """Zero-force frames only count for MAE; frames under 2 N skip CoP and IoU."""
    weak = disk(1.0)  # 1 N < MIN_SHAPE_FORCE_N
    none = np.zeros_like(weak)
    gt = np.concatenate([weak, none])
    pred = np.concatenate([2 * weak, np.full_like(weak, 0.5)])
    m = compute_metrics(pred, gt, np.zeros((2, 2)), G)
    assert MIN_SHAPE_FORCE_N == 2.0
    assert m["frames"] == 2 and m["force_frames"] == 1
    assert m["cop_frames"] == m["iou_frames"] == 0
    assert m["cop_error_mm"] is None and m["iou"] is None
    assert m["force_error_pct"] == pytest.approx(100.0)  # |2F - F| / F
    expected_mae = (float(weak.mean(dtype=np.float64)) + 0.5) / 2
    assert m["mae_kpa"] == pytest.approx(expected_mae, rel=1e-6)
    strict_json(m)


def test_non_finite_prediction_is_refused():
    gt = disk(5.0)
    pred = gt.copy()
    pred[0, 3, 3] = np.nan
    with pytest.raises(ValueError, match="pred_kpa.*non-finite"):
        compute_metrics(pred, gt, np.zeros((1, 2)), G)


# --- Otsu ---------------------------------------------------------------------------
def test_otsu_two_levels():
    img = np.zeros((1, 20, 30))
    img[0, 5:10, 4:20] = 7.0
    mask = otsu_masks(img)
    np.testing.assert_array_equal(mask, img > 0)
    t = otsu_thresholds(img)[0]
    assert 0.0 <= t < 7.0


def test_otsu_matches_opencv_on_uint8():
    rng = np.random.default_rng(1)
    values = np.concatenate([rng.normal(60, 12, 3000), rng.normal(170, 15, 1000)])
    img = rng.permutation(values).clip(0, 255).astype(np.uint8).reshape(1, 50, 80)
    t_cv, _ = cv2.threshold(img[0], 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    np.testing.assert_array_equal(otsu_masks(img)[0], img[0] > t_cv)


def brute_force_otsu_mask(values: np.ndarray) -> np.ndarray:
    """Exact Otsu: try every split between consecutive distinct values."""
    levels = np.unique(values)
    best, best_t = -1.0, levels[0]
    for lo, hi in zip(levels[:-1], levels[1:], strict=True):
        t = (lo + hi) / 2
        a, b = values[values <= t], values[values > t]
        between = a.size * b.size * (a.mean() - b.mean()) ** 2
        if between > best:
            best, best_t = between, t
    return values > best_t


def test_otsu_matches_brute_force_on_three_clusters():
    rng = np.random.default_rng(2)
    values = np.concatenate(
        [rng.uniform(0, 1, 500), rng.uniform(20, 21, 120), rng.uniform(40, 41, 380)]
    )
    img = rng.permutation(values).reshape(1, 25, 40)
    np.testing.assert_array_equal(otsu_masks(img)[0], brute_force_otsu_mask(img[0]))


def test_otsu_constant_and_scale_invariance():
    assert not otsu_masks(np.zeros((2, 8, 8))).any()
    assert not otsu_masks(np.full((1, 8, 8), 3.0)).any()
    rng = np.random.default_rng(3)
    img = rng.gamma(2.0, size=(3, 16, 16))
    np.testing.assert_array_equal(otsu_masks(img), otsu_masks(img * 5 + 2))


def test_contact_iou_values():
    a = np.zeros((1, 10, 20), bool)
    b = np.zeros((1, 10, 20), bool)
    a[0, :, 0:10] = True  # 100 px
    b[0, :, 5:15] = True  # 100 px, 50 shared
    assert contact_iou(a, b)[0] == pytest.approx(50 / 150)
    assert contact_iou(a[:, :0], b[:, :0])[0] == 1.0  # two empty masks agree


def test_iou_of_shifted_square():
    gt = np.zeros((1, 64, 64))
    gt[0, 20:30, 20:30] = 100.0  # 100 px * 0.41 mm^2 * 100 kPa = 4.1 N
    pred = np.roll(gt, 5, axis=2)
    m = compute_metrics(pred, gt, np.zeros((1, 2)), G)
    assert m["iou"] == pytest.approx(50 / 150)


# --- regions ------------------------------------------------------------------------
def test_region_cells():
    pos = np.array(
        [
            [15.0, 15.0],  # printer +X, +Y: image top-left
            [-15.0, -15.0],  # bottom-right
            [-5.0, 5.0],  # row band 1 (y in 0..10.25), column band 2 (x in -10.25..0)
            [0.0, 0.0],  # on the corner of four cells: the higher ones
            [30.0, -30.0],  # outside the field: clipped to the edge
            [10.0, -10.0],
        ]
    )
    np.testing.assert_array_equal(
        region_cells(pos, G), [[0, 0], [3, 3], [1, 2], [2, 2], [3, 0], [2, 1]]
    )
    # The same cells at any image size: the grid is in mm (10.25 mm cells).
    np.testing.assert_array_equal(region_cells(pos, G.with_image_size(256)), region_cells(pos, G))


def test_region_mae_groups_by_true_position():
    gt = np.concatenate([disk(10.0), disk(10.0), disk(10.0)])
    pred = gt.copy()
    pred[1] += 1.0  # MAE 1 kPa
    pred[2] += 3.0  # MAE 3 kPa
    pos = np.array([[15.0, 15.0], [15.0, 15.0], [-15.0, -15.0]])
    m = compute_metrics(pred, gt, pos, G)
    region = m["region_mae_kpa"]
    assert region[0][0] == pytest.approx(0.5)
    assert region[3][3] == pytest.approx(3.0)
    assert region[1][1] is None
    assert m["region_frames"][0][0] == 2 and m["region_frames"][3][3] == 1
    assert m["worst_region_mae_kpa"] == pytest.approx(3.0)
    assert m["worst_region_cell"] == [3, 3]
    assert sum(v is None for row in region for v in row) == 14
    strict_json(m)


def test_no_press_frames_gives_nulls_where_undefined():
    gt = np.zeros((2, 64, 64), np.float32)
    m = compute_metrics(gt + 0.25, gt, np.array([[-15.0, 15.0], [-15.0, 15.0]]), G)
    assert m["mae_kpa"] == pytest.approx(0.25)
    assert m["force_error_pct"] is None and m["cop_error_mm"] is None and m["iou"] is None
    # Regions count every frame by its press position: out-of-contact frames too.
    assert m["worst_region_mae_kpa"] == pytest.approx(0.25) and m["worst_region_cell"] == [0, 3]
    assert sum(v is None for row in m["region_mae_kpa"] for v in row) == 15
    strict_json(m)


def test_streaming_equals_one_batch():
    rng = np.random.default_rng(4)
    force = rng.uniform(0, 12, 10)
    force[[2, 7]] = 0.0
    xy = rng.uniform(-13, 13, (10, 2))
    gt = disk_maps(force, xy, G)
    pred = np.clip(gt + rng.normal(0, 2, gt.shape), 0, None).astype(np.float32)
    pred[5] = 0.0
    acc = MetricsAccumulator(G)
    for i in range(0, 10, 3):
        acc.update(pred[i : i + 3], gt[i : i + 3], xy[i : i + 3])
    streamed, whole = acc.result(), compute_metrics(pred, gt, xy, G)
    assert streamed.keys() == whole.keys()
    for key, value in whole.items():
        if isinstance(value, float):
            assert streamed[key] == pytest.approx(value, rel=1e-9), key
        else:
            assert streamed[key] == value, key
    per_frame = np.abs(pred.astype(np.float64) - gt).mean(axis=(1, 2))
    assert whole["mae_kpa"] == pytest.approx(per_frame.mean())


def test_format_metrics_table():
    m = compute_metrics(disk(10.0) * 1.2, disk(10.0), np.zeros((1, 2)), G)
    m_none = dict(m, cop_error_mm=None)
    text = format_metrics_table(m_none, baselines={"zero": m})
    lines = text.splitlines()
    assert "this run" in lines[0] and "paper" in lines[0] and "baseline: zero" in lines[0]
    force_row = next(ln for ln in lines if ln.startswith("total-force error"))
    assert force_row.split()[-3:] == ["20.0", "11.9", "20.0"]
    cop_row = next(ln for ln in lines if ln.startswith("centre of pressure"))
    assert "n/a" in cop_row and "1.18" in cop_row
    for value in ("0.790", "0.810", "1.050"):
        assert value in text
    assert math.isfinite(m["mae_kpa"])


def test_the_gated_metrics_are_the_papers():
    from beadsight.metrics import PAPER_METRIC_KEYS
    from beadsight.report.paper import PAPER_METRICS

    assert tuple(PAPER_METRICS) == PAPER_METRIC_KEYS
