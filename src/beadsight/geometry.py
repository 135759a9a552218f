"""Sensor geometry: mm <-> pixels, pressure disks, force, centre of pressure, Otsu contact.

Conventions
-----------
* Positions ``xy_mm`` are millimetres from the sensor centre in the printer frame.
* Pixel coordinates are continuous ``(row, col)``; pixel ``i`` covers ``[i, i+1)`` so
  its centre is ``i + 0.5`` and the image centre is ``image_size_px / 2``.
* Printer +X -> image -column, printer +Y -> image -row (reference convention):
  ``row = (1 - (0.5 + y/S)) * N``, ``col = (1 - (0.5 + x/S)) * N``.
* Pressure maps are float32 kPa; forces are newtons.

Every function accepts numpy arrays; :func:`disk_maps` and the map reductions
also accept torch tensors (so ground truth can be built on a GPU) and return the
same type they were given.
"""

from __future__ import annotations

import functools
import math
from typing import TypeVar

import numpy as np

from beadsight.config import REFERENCE_G_TO_N, SensorGeometry

Array = TypeVar("Array")

PA_PER_KPA = 1000.0
OTSU_BINS = 256  # histogram bins of the Otsu threshold


# --- units --------------------------------------------------------------------------
def grams_to_newtons(grams, g_to_n: float = REFERENCE_G_TO_N):
    """Scale readings in grams -> newtons (reference factor 9.81e-3 N/g)."""
    return grams * g_to_n


def newtons_to_grams(newtons, g_to_n: float = REFERENCE_G_TO_N):
    return newtons / g_to_n


def force_to_newtons(values, unit: str):
    """Convert forces in ``unit`` ("g", "kg", "N", "mN") to newtons."""
    factors = {"g": REFERENCE_G_TO_N, "kg": 1000 * REFERENCE_G_TO_N, "n": 1.0, "mn": 1e-3}
    key = unit.strip().lower()
    if key not in factors:
        raise ValueError(f"unknown force unit {unit!r}; expected one of g, kg, N, mN")
    return values * factors[key]


def pressure_to_kpa(values, unit: str):
    """Convert pressures in ``unit`` ("Pa", "kPa") to kPa."""
    key = unit.strip().lower()
    if key == "pa":
        return values / PA_PER_KPA
    if key == "kpa":
        return values
    raise ValueError(f"unknown pressure unit {unit!r}; expected Pa or kPa")


def disk_pressure_kpa(force_n, geometry: SensorGeometry):
    """Uniform pressure (kPa) of ``force_n`` spread over the finger's disk: F / (pi r^2)."""
    area_m2 = math.pi * (geometry.finger_radius_mm * 1e-3) ** 2
    return force_n / area_m2 / PA_PER_KPA


# --- coordinates --------------------------------------------------------------------
def mm_to_px(xy_mm, geometry: SensorGeometry) -> np.ndarray:
    """``(..., 2)`` printer-frame mm (x, y) -> ``(..., 2)`` continuous pixel (row, col)."""
    xy = np.asarray(xy_mm, dtype=np.float64)
    n, s = geometry.image_size_px, geometry.sensor_size_mm
    row = (1.0 - (0.5 + xy[..., 1] / s)) * n
    col = (1.0 - (0.5 + xy[..., 0] / s)) * n
    return np.stack([row, col], axis=-1)


def px_to_mm(rc_px, geometry: SensorGeometry) -> np.ndarray:
    """``(..., 2)`` continuous pixel (row, col) -> ``(..., 2)`` printer-frame mm (x, y)."""
    rc = np.asarray(rc_px, dtype=np.float64)
    n, s = geometry.image_size_px, geometry.sensor_size_mm
    y = (0.5 - rc[..., 0] / n) * s
    x = (0.5 - rc[..., 1] / n) * s
    return np.stack([x, y], axis=-1)


def _pixel_centres_mm(geometry: SensorGeometry) -> tuple[np.ndarray, np.ndarray]:
    """x_mm of each column centre, y_mm of each row centre (printer frame)."""
    n, s = geometry.image_size_px, geometry.sensor_size_mm
    centres = (np.arange(n) + 0.5) / n
    return (0.5 - centres) * s, (0.5 - centres) * s  # (x of col, y of row)


# --- ground truth -------------------------------------------------------------------
def disk_maps(force_n, xy_mm, geometry: SensorGeometry):
    """Uniform-pressure finger disks, anti-aliased by pixel coverage.

    force_n: (B,) newtons (numpy or torch). xy_mm: (B, 2) finger centre, mm.
    returns: (B, H, W) float32 kPa, same array type and device as ``force_n``.
    Each pixel holds P * coverage, where coverage in [0, 1] is the fraction of the
    pixel inside the disk (linear ramp over one pixel at the rim), so the map's
    integral equals the force to well under 1 % for a disk inside the field.
    Zero or negative forces give all-zero maps.
    """
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a core dependency
        torch = None
    if torch is not None and isinstance(force_n, torch.Tensor):
        return _disk_maps_torch(force_n, xy_mm, geometry)
    force = np.asarray(force_n, dtype=np.float64).reshape(-1)
    xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
    if len(force) != len(xy):
        raise ValueError(f"force_n has {len(force)} entries but xy_mm has {len(xy)}")
    x_col, y_row = _pixel_centres_mm(geometry)
    mm_per_px = geometry.mm_per_px
    dx = x_col[None, None, :] - xy[:, 0, None, None]
    dy = y_row[None, :, None] - xy[:, 1, None, None]
    dist_px = np.sqrt(dx * dx + dy * dy) / mm_per_px
    coverage = np.clip(geometry.finger_radius_mm / mm_per_px - dist_px + 0.5, 0.0, 1.0)
    pressure = disk_pressure_kpa(np.clip(force, 0.0, None), geometry)
    return (coverage * pressure[:, None, None]).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _pixel_centres_tensors(geometry: SensorGeometry, device: str):
    """Cached device copies of :func:`_pixel_centres_mm` (no host->device copy per batch)."""
    import torch

    return tuple(
        torch.as_tensor(a, device=device, dtype=torch.float32) for a in _pixel_centres_mm(geometry)
    )


def _disk_maps_torch(force_n, xy_mm, geometry: SensorGeometry):
    import torch

    force = force_n.reshape(-1).to(torch.float32)
    xy = torch.as_tensor(xy_mm, device=force.device, dtype=torch.float32).reshape(-1, 2)
    x_col, y_row = _pixel_centres_tensors(geometry, str(force.device))
    dx = x_col[None, None, :] - xy[:, 0, None, None]
    dy = y_row[None, :, None] - xy[:, 1, None, None]
    dist_px = torch.sqrt(dx * dx + dy * dy) / geometry.mm_per_px
    coverage = (geometry.finger_radius_mm / geometry.mm_per_px - dist_px + 0.5).clamp(0.0, 1.0)
    return coverage * disk_pressure_kpa(force.clamp(min=0.0), geometry)[:, None, None]


# --- reductions of pressure maps ----------------------------------------------------
def total_force_n(maps_kpa, geometry: SensorGeometry):
    """Integral of ``(..., H, W)`` kPa maps -> ``(...)`` newtons."""
    scale = PA_PER_KPA * geometry.with_image_size(maps_kpa.shape[-1]).pixel_area_m2
    return (
        maps_kpa.sum(axis=(-2, -1)) * scale
        if isinstance(maps_kpa, np.ndarray)
        else (maps_kpa.sum(dim=(-2, -1)) * scale)
    )


def centre_of_pressure_mm(maps_kpa, geometry: SensorGeometry) -> np.ndarray:
    """Pressure-weighted centroid of ``(..., H, W)`` maps -> ``(..., 2)`` mm (x, y).

    Negative values are ignored. A map with no positive pressure has no centre:
    its entry is NaN (callers decide how to treat it; metrics exclude such frames
    or count them as misses explicitly).
    """
    maps = np.clip(np.asarray(maps_kpa, dtype=np.float64), 0.0, None)
    g = geometry.with_image_size(maps.shape[-1])
    x_col, y_row = _pixel_centres_mm(g)
    total = maps.sum(axis=(-2, -1))
    with np.errstate(invalid="ignore", divide="ignore"):
        x = (maps.sum(axis=-2) * x_col).sum(axis=-1) / total
        y = (maps.sum(axis=-1) * y_row).sum(axis=-1) / total
    out = np.stack([x, y], axis=-1)
    out[total <= 0] = np.nan
    return out


def contact_area_mm2(mask, geometry: SensorGeometry):
    """Area of a ``(..., H, W)`` boolean contact mask in mm^2."""
    g = geometry.with_image_size(mask.shape[-1])
    return np.asarray(mask).sum(axis=(-2, -1)) * g.mm_per_px**2


# --- Otsu ---------------------------------------------------------------------------
def _otsu_bins(maps: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-map histogram bin index of every pixel, the split bin k, and the span.

    maps: (B, H, W). returns: idx (B, H*W) int64 in 0..bins-1, k (B,) int64 (class 0 =
    bins <= k), span (B,) float64 (max - min; 0 for constant maps).
    """
    x = maps.reshape(len(maps), -1).astype(np.float64)
    lo, hi = x.min(axis=1), x.max(axis=1)
    span = hi - lo
    scale = np.divide(bins, span, out=np.zeros_like(span), where=span > 0)
    idx = np.clip(((x - lo[:, None]) * scale[:, None]).astype(np.int64), 0, bins - 1)
    offsets = np.arange(len(maps), dtype=np.int64)[:, None] * bins
    hist = np.bincount((idx + offsets).ravel(), minlength=len(maps) * bins)
    hist = hist.reshape(len(maps), bins).astype(np.float64)
    centres = np.arange(bins, dtype=np.float64) + 0.5  # bin units: the scale cancels out
    w0 = np.cumsum(hist, axis=1)
    s0 = np.cumsum(hist * centres, axis=1)
    w1 = w0[:, -1:] - w0
    s1 = s0[:, -1:] - s0
    with np.errstate(invalid="ignore", divide="ignore"):
        between = w0 * w1 * (s0 / w0 - s1 / w1) ** 2  # between-class variance * n^2
    between = np.nan_to_num(between[:, :-1], nan=-1.0)
    return idx, np.argmax(between, axis=1), span


def otsu_thresholds(maps: np.ndarray, bins: int = OTSU_BINS) -> np.ndarray:
    """Otsu's threshold of each map: (B, H, W) -> (B,) float64, same unit as the maps.

    The threshold maximises the between-class variance of a ``bins``-bin histogram
    spanning each map's [min, max]; it is the upper edge of the last background
    bin, so the foreground is ``map > threshold`` (up to values exactly on that
    edge; :func:`otsu_masks` gives the exact partition). A constant map returns its
    value (empty foreground).
    """
    maps = np.asarray(maps)
    _, k, span = _otsu_bins(maps, bins)
    lo = maps.reshape(len(maps), -1).min(axis=1).astype(np.float64)
    return np.where(span > 0, lo + (k + 1) * span / bins, lo)


def otsu_masks(maps: np.ndarray, bins: int = OTSU_BINS) -> np.ndarray:
    """Foreground of each map by Otsu's method: (B, H, W) -> (B, H, W) bool.

    Pixels in histogram bins above the Otsu split. Constant maps (including
    all-zero predictions) have an empty foreground.
    """
    maps = np.asarray(maps)
    idx, k, span = _otsu_bins(maps, bins)
    mask = (idx > k[:, None]) & (span[:, None] > 0)
    return mask.reshape(maps.shape)
