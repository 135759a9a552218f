"""The reference's processed HDF5 layout: import it into ours, export ours into it.

The layout is the one the reference's ``raw_data_process.py`` writes (reference-facts
section 6), so the reference training and evaluation scripts read an exported file:

=============  ===============  ========  ==========================================
dataset        shape            dtype     content (HDF5 chunks)
=============  ===============  ========  ==========================================
``images``     (N, S, S, 3)     uint8     BGR frames, chunks (1, S, S, 3), gzip level
                                          ``compression_level`` when > 0
``forces``     (N,)             float32   grams; 0.0 where the force is unknown, (1,)
``position``   (N, 2)           float32   mm from the sensor centre; frames with no
                                          press position hold (-1, -1) minus the
                                          centre, as the reference writes them, (1, 2)
``valid``      (N,)             bool      (1,)
``time``       (N,)             float32   unix seconds (float32, as the reference), (1,)
=============  ===============  ========  ==========================================

File attributes: the experiment parameters (``resolution`` [S, S], ``fps``,
``contact_radius``, ``sensor_size`` [w, w], ``force_unit`` "g", ``dist_unit`` "mm",
``center`` printer XY, ``radius`` press range), then ``start_time`` 0, ``end_time``
-1, ``compression_level``, ``pixel_mean`` / ``pixel_std`` (float64, BGR, over all
frames) and ``average_force`` (float32, the mean of ``forces``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np

from beadsight.config import REFERENCE_CENTRE_XY_MM, REFERENCE_G_TO_N
from beadsight.data.dataset import Dataset, DatasetError, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.files import (
    WriteError,
    describe_write_failure,
    finish_partial,
    os_errors_as_write_errors,
    partial_path,
    refuse_existing,
)

EXPORT_FORMATS = ("reference",)
NO_POSITION_XY = -1.0  # the reference's printer position for frames not at a press
READ_BLOCK = 256  # frames per read/write


def import_reference(src: str | Path, dst: str | Path, chunk: int = READ_BLOCK) -> Path:
    """Convert a reference processed HDF5 file to this project's format (frames -> RGB)."""
    with open_dataset(src) as ds:
        if not ds.is_reference:
            raise DatasetError(f"{src}: already a beadsight dataset; nothing to import")
        fps = ds.fps
        with DatasetWriter(
            dst,
            ds.geometry,
            fps=fps,
            provenance={"source": "reference-import", "imported_from": str(src)},
        ) as w:
            for i in range(0, len(ds), chunk):
                j = min(i + chunk, len(ds))
                w.append(
                    ds.read_frames(i, j),
                    ds.force_n[i:j],
                    ds.position_mm[i:j],
                    ds.valid[i:j],
                    ds.timestamp_s[i:j],
                )
    return Path(dst)


def _number(v: float) -> int | float:
    """An integral value as int (the reference's JSON parameters hold 30, 41, ...)."""
    v = float(v)
    return int(v) if v.is_integer() else v


def experiment_parameters(ds: Dataset) -> dict[str, Any]:
    """The reference's ``experiment_parameters.json`` entries for dataset ``ds``."""
    g = ds.geometry
    centre = ds.provenance.get("centre_xy_mm") or REFERENCE_CENTRE_XY_MM
    return {
        "resolution": [ds.image_size, ds.image_size],
        "fps": _number(ds.fps),
        "contact_radius": _number(g.finger_radius_mm),
        "sensor_size": [_number(g.sensor_size_mm)] * 2,
        "force_unit": "g",
        "dist_unit": "mm",
        "center": [float(c) for c in centre],
        "radius": _number(g.press_range_mm),
    }


def reference_columns(ds: Dataset, centre: np.ndarray) -> dict[str, np.ndarray]:
    """forces (g), position (mm), valid, time as the reference stores them (float32)."""
    grams = np.where(np.isfinite(ds.force_n), ds.force_n / REFERENCE_G_TO_N, 0.0)
    no_press = np.full(2, NO_POSITION_XY) - centre
    known = np.isfinite(ds.position_mm).all(axis=1)
    position = np.where(known[:, None], ds.position_mm, no_press[None])
    return {
        "forces": _float32(ds, "forces", grams),
        "position": _float32(ds, "position", position),
        "valid": ds.valid.astype(bool),
        "time": _float32(ds, "time", ds.timestamp_s),
    }


def _float32(ds: Dataset, name: str, values: np.ndarray) -> np.ndarray:
    """``values`` as float32; DatasetError naming the column and frame for a finite value
    that float32 cannot hold (it would be written as inf, which readers refuse)."""
    limit = np.finfo(np.float32).max
    lost = np.isfinite(values) & (np.abs(values) > limit)
    if lost.any():
        frame = int(np.flatnonzero(lost.reshape(len(values), -1).any(axis=1))[0])
        raise DatasetError(
            f"{ds.path}: frame {frame}: {name} {values[frame]} does not fit the reference "
            f"layout's float32 (|x| <= {limit:.3g}); fix or drop that frame"
        )
    return values.astype(np.float32)


def export_reference(
    src: str | Path, dst: str | Path, *, compression_level: int = 0, overwrite: bool = False
) -> Path:
    """Write dataset ``src`` in the reference layout (module docstring) at ``dst``.

    The file is written as ``<dst>.partial`` and renamed when complete; a write
    failure raises WriteError and leaves no file named ``dst``.
    """
    dst = refuse_existing(dst, overwrite)
    if not 0 <= int(compression_level) <= 9:
        raise DatasetError(f"compression_level must be 0..9 (gzip), got {compression_level}")
    partial = partial_path(dst)
    with os_errors_as_write_errors(partial):
        dst.parent.mkdir(parents=True, exist_ok=True)
    with open_dataset(src) as ds:
        if ds.is_reference:
            raise DatasetError(f"{src}: already in the reference layout; nothing to export")
        params = experiment_parameters(ds)
        columns = reference_columns(ds, np.asarray(params["center"], np.float64))
        try:
            with h5py.File(partial, "w") as f:
                _write_reference(f, ds, params, columns, int(compression_level))
        except (OSError, RuntimeError) as e:
            raise WriteError(
                f"could not write {partial}: {describe_write_failure(e)}; {dst} was not written"
            ) from e
    return finish_partial(partial, dst)


def _write_reference(
    f: h5py.File, ds: Dataset, params: dict, columns: dict[str, np.ndarray], level: int
) -> None:
    n, s = len(ds), ds.image_size
    images = f.create_dataset(
        "images",
        shape=(n, s, s, 3),
        chunks=(1, s, s, 3),
        dtype=np.uint8,
        **({"compression": level} if level > 0 else {}),
    )
    for name, values in columns.items():
        f.create_dataset(name, data=values, chunks=(1, *values.shape[1:]))
    f.attrs.update(params)
    f.attrs["start_time"] = 0
    f.attrs["end_time"] = -1
    f.attrs["compression_level"] = level
    total, total_sq = np.zeros(3), np.zeros(3)
    for i in range(0, n, READ_BLOCK):
        bgr = ds.read_frames(i, min(i + READ_BLOCK, n))[..., ::-1]
        images[i : i + len(bgr)] = np.ascontiguousarray(bgr)
        pixels = bgr.reshape(-1, 3).astype(np.float64)
        total += pixels.sum(axis=0)
        total_sq += (pixels * pixels).sum(axis=0)
    count = max(n * s * s, 1)
    mean = total / count
    f.attrs["pixel_mean"] = mean
    f.attrs["pixel_std"] = np.sqrt(np.maximum(total_sq / count - mean**2, 0.0))
    f.attrs["average_force"] = np.mean(columns["forces"])
