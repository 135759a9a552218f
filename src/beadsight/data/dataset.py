"""The BeadSight dataset (HDF5): reading.

See docs/data-format.md for the layout. :func:`open_dataset` reads this project's
files and the reference processed files alike and presents them through one
:class:`Dataset` object (forces in newtons, positions in mm, float64 timestamps,
press segmentation). Writing: :class:`beadsight.data.dataset_writer.DatasetWriter`; the
reference layout: :mod:`beadsight.data.reference_file`.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from beadsight.config import ContactThresholds, SensorGeometry
from beadsight.data.plausibility import ABSURD_FORCE_N, ABSURD_POSITION_MM
from beadsight.data.presses import segment_presses
from beadsight.errors import BeadSightError
from beadsight.files import Closes
from beadsight.geometry import force_to_newtons
from beadsight.h5safe import find_dataset, open_h5

FORMAT = "beadsight-dataset"
FORMAT_VERSION = 1
FINGERPRINT_SAMPLE_FRAMES = 4  # frames hashed (besides all labels) in a dataset fingerprint
MAX_FPS = 10_000.0  # frames per second beyond any camera's: a corrupt attribute
MIN_FORCE_N = -5.0  # lower at a valid frame is no scale's tare drift: a wrong sign or unit


class DatasetError(BeadSightError, ValueError):
    """A dataset file is missing, corrupt, foreign, or inconsistent; the message names it."""


@dataclass
class Dataset(Closes):
    """An open dataset. Arrays are loaded; ``frames`` stays on disk (h5py dataset).

    frames: (N, H, W, 3) uint8 in ``channel_order`` ("RGB" or "BGR").
    force_n: (N,) float64 N; position_mm: (N, 2) float64 mm (printer frame);
    valid: (N,) bool; timestamp_s: (N,) float64 s (unix); contact: (N,) bool;
    press_id: (N,) int32 press cycle of each frame (-1 if none); presses: (P, 2)
    ``[start, stop)`` contact ranges.
    """

    path: Path
    frames: h5py.Dataset
    channel_order: str
    force_n: np.ndarray
    position_mm: np.ndarray
    valid: np.ndarray
    timestamp_s: np.ndarray
    contact: np.ndarray
    press_id: np.ndarray
    presses: np.ndarray
    geometry: SensorGeometry
    fps: float
    pixel_mean: np.ndarray | None  # (3,) in channel_order, 0..255
    pixel_std: np.ndarray | None
    provenance: dict[str, Any]
    is_reference: bool
    _file: h5py.File

    def __len__(self) -> int:
        return len(self.force_n)

    @property
    def num_presses(self) -> int:
        return len(self.presses)

    @property
    def image_size(self) -> int:
        return int(self.frames.shape[1])

    def read_frames(self, start: int, stop: int) -> np.ndarray:
        """Frames ``[start, stop)`` as (n, H, W, 3) uint8 **RGB**."""
        block = self.frames[start:stop]
        return block[..., ::-1].copy() if self.channel_order == "BGR" else block

    def read_frames_at(self, index: np.ndarray) -> np.ndarray:
        """Frames at sorted or unsorted indices as (n, H, W, 3) uint8 RGB."""
        index = np.asarray(index)
        order = np.argsort(index)
        block = np.empty((len(index), *self.frames.shape[1:]), dtype=np.uint8)
        block[order] = self.frames[index[order]]
        return block[..., ::-1].copy() if self.channel_order == "BGR" else block

    def rgb_pixel_stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-channel mean/std in RGB order (computed from a frame sample if not stored)."""
        if self.pixel_mean is not None and self.pixel_std is not None:
            mean, std = self.pixel_mean, self.pixel_std
        else:
            idx = np.unique(np.linspace(0, len(self) - 1, min(len(self), 256)).astype(int))
            sample = self.frames[idx].reshape(-1, 3).astype(np.float64)
            mean, std = sample.mean(0), sample.std(0)
        if self.channel_order == "BGR":
            mean, std = mean[::-1], std[::-1]
        return np.asarray(mean, np.float64).copy(), np.maximum(np.asarray(std, np.float64), 1e-3)

    def require_presses(self) -> None:
        if self.num_presses == 0:
            raise DatasetError(
                f"{self.path}: no presses found (force never reaches contact while frames are "
                "valid); a dataset for training or evaluation needs at least one press"
            )

    def close(self) -> None:
        self._file.close()


# --- reading ------------------------------------------------------------------------
def _get(f: h5py.File, path: Path, names: tuple[str, ...], expected: str) -> h5py.Dataset:
    """The first of ``names`` as a dataset whose claimed size the file holds (h5safe)."""
    ds = find_dataset(f, names, path, DatasetError, expected)
    if ds is None:
        raise DatasetError(f"{path}: missing dataset '{names[0]}' (expected {expected})")
    return ds


def _attr_json(f: h5py.File, key: str, default: Any) -> Any:
    if key not in f.attrs:
        return default
    value = f.attrs[key]
    if isinstance(value, bytes):
        value = value.decode()
    return json.loads(value) if isinstance(value, str) else value


def _reference_geometry(f: h5py.File, image_size: int) -> SensorGeometry:
    g = SensorGeometry(image_size_px=image_size)
    kwargs = g.to_dict()
    if "sensor_size" in f.attrs:
        kwargs["sensor_size_mm"] = float(np.asarray(f.attrs["sensor_size"]).reshape(-1)[0])
    if "contact_radius" in f.attrs:
        kwargs["finger_radius_mm"] = float(np.asarray(f.attrs["contact_radius"]).reshape(-1)[0])
    if "radius" in f.attrs:
        kwargs["press_range_mm"] = float(np.asarray(f.attrs["radius"]).reshape(-1)[0])
    return SensorGeometry.from_dict(kwargs)


def open_dataset(path: str | Path, thresholds: ContactThresholds = ContactThresholds()) -> Dataset:
    """Open a beadsight dataset or a reference processed HDF5 file for reading."""
    path = Path(path)
    f = open_h5(path, "dataset file", DatasetError)
    try:
        return _read(f, path, thresholds)
    except DatasetError:
        f.close()
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        f.close()
        raise DatasetError(f"{path}: unreadable dataset ({type(e).__name__}: {e})") from None


def _read(f: h5py.File, path: Path, thresholds: ContactThresholds) -> Dataset:
    is_reference = _check_format(f, path)
    frames = _frames(f, path, is_reference)
    load = _loader(f, path, frames.shape[0])
    fields = (_reference_fields if is_reference else _fields)(f, path, frames, load)
    force, position, valid = fields["force_n"], fields["position_mm"], fields["valid"]
    bad = np.flatnonzero(valid & ~np.isfinite(force))
    if len(bad):
        raise DatasetError(
            f"{path}: field 'force' has {len(bad)} NaN/inf values at valid frames (first at frame "
            f"{bad[0]}); expected finite newtons, or mark those frames invalid"
        )
    bad = np.flatnonzero(valid & ~np.isfinite(position).all(axis=1))
    if len(bad):
        raise DatasetError(
            f"{path}: field 'position' has non-finite values at valid frames (first at frame {bad[0]})"
        )
    _check_ranges(path, fields)
    contact, press_id, presses = segment_presses(force, valid, position, thresholds)
    mean, std = fields.pop("pixel_mean"), fields.pop("pixel_std")
    return Dataset(
        path=path,
        frames=frames,
        contact=contact,
        press_id=press_id,
        presses=presses,
        pixel_mean=None if mean is None else np.asarray(mean, np.float64).reshape(3),
        pixel_std=None if std is None else np.asarray(std, np.float64).reshape(3),
        is_reference=is_reference,
        _file=f,
        **fields,
    )


def _check_ranges(path: Path, fields: dict[str, Any]) -> None:
    """DatasetError naming the field unless fps, and force and position at valid frames, are
    in the ranges a real rig produces (a corrupt or forged file otherwise)."""
    fps = fields["fps"]
    if not 0 < fps <= MAX_FPS:
        raise DatasetError(
            f"{path}: attribute 'fps' is {fps:g}; expected frames per second > 0 and <= {MAX_FPS:g}"
        )
    valid = fields["valid"]
    for name, values, low, high, unit in (
        ("force", fields["force_n"], MIN_FORCE_N, ABSURD_FORCE_N, "N"),
        ("position", fields["position_mm"], -ABSURD_POSITION_MM, ABSURD_POSITION_MM, "mm"),
    ):
        inside = (values >= low) & (values <= high)
        bad = np.flatnonzero(valid & ~(inside.all(axis=1) if inside.ndim > 1 else inside))
        if len(bad):
            raise DatasetError(
                f"{path}: field '{name}' has {len(bad)} valid frame(s) outside {low:g} .. "
                f"{high:g} {unit} (first at frame {bad[0]}: {values[bad[0]]}); expected a "
                "rig's readings, or mark those frames invalid"
            )


def _check_format(f: h5py.File, path: Path) -> bool:
    """True for the reference's processed layout; DatasetError for anything unknown."""
    fmt = f.attrs.get("format")
    is_reference = fmt is None and "images" in f
    if fmt is None and not is_reference:
        raise DatasetError(
            f"{path}: not a BeadSight dataset: no 'format' attribute and no 'images' dataset "
            f"(found: {sorted(f.keys())[:8]})"
        )
    if fmt is not None and (fmt.decode() if isinstance(fmt, bytes) else fmt) != FORMAT:
        raise DatasetError(f"{path}: attribute 'format' is {fmt!r}, expected {FORMAT!r}")
    if not is_reference and int(f.attrs.get("format_version", 0)) > FORMAT_VERSION:
        raise DatasetError(
            f"{path}: format_version {f.attrs['format_version']} is newer than this beadsight "
            f"reads ({FORMAT_VERSION}); upgrade beadsight"
        )
    return is_reference


def _frames(f: h5py.File, path: Path, is_reference: bool) -> h5py.Dataset:
    frames = _get(
        f, path, ("images",) if is_reference else ("frames",), "(N, H, W, 3) uint8 frames"
    )
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[1] != frames.shape[2]:
        raise DatasetError(
            f"{path}: '{frames.name[1:]}' has shape {frames.shape}; expected (N, S, S, 3)"
        )
    if frames.dtype != np.uint8:
        raise DatasetError(f"{path}: '{frames.name[1:]}' has dtype {frames.dtype}; expected uint8")
    return frames


def _loader(f: h5py.File, path: Path, n: int):
    """``load(names, expected, shape)``: a whole field, its shape checked (rows = ``n``)."""

    def load(names: tuple[str, ...], expected: str, shape: tuple[int, ...]) -> np.ndarray:
        ds = _get(f, path, names, expected)
        if ds.shape != shape:
            raise DatasetError(
                f"{path}: '{ds.name[1:]}' has shape {ds.shape}; expected {shape} ({expected})"
            )
        return ds[()]

    return load


def _text(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _reference_fields(f: h5py.File, path: Path, frames: h5py.Dataset, load) -> dict[str, Any]:
    """The reference's layout: grams (or its force_unit), BGR frames, float32 unix times."""
    n = frames.shape[0]
    raw_force = load(("forces",), "(N,) force readings", (n,))
    return {
        "force_n": force_to_newtons(
            raw_force.astype(np.float64), _text(f.attrs.get("force_unit", "g"))
        ),
        "position_mm": load(("position",), "(N, 2) mm", (n, 2)).astype(np.float64),
        "valid": load(("valid",), "(N,) bool", (n,)).astype(bool),
        "timestamp_s": load(("time",), "(N,) unix seconds", (n,)).astype(np.float64),
        "channel_order": "BGR",
        "geometry": _reference_geometry(f, frames.shape[1]),
        "fps": float(np.asarray(f.attrs.get("fps", 30.0)).reshape(-1)[0]),
        "provenance": {"source": "reference", "file": str(path)},
        "pixel_mean": f.attrs.get("pixel_mean"),
        "pixel_std": f.attrs.get("pixel_std"),
    }


def _fields(f: h5py.File, path: Path, frames: h5py.Dataset, load) -> dict[str, Any]:
    """This project's layout (docs/data-format.md)."""
    n = frames.shape[0]
    unit = _get(f, path, ("force",), "(N,) float64 force").attrs.get("unit", "N")
    channel_order = _text(frames.attrs.get("channel_order", "RGB"))
    if channel_order not in ("RGB", "BGR"):
        raise DatasetError(
            f"{path}: frames attribute 'channel_order' is {channel_order!r}; expected RGB or BGR"
        )
    try:
        geometry = SensorGeometry.from_dict(_attr_json(f, "geometry", {}))
    except (ValueError, TypeError) as e:
        raise DatasetError(f"{path}: attribute 'geometry': {e}") from None
    if geometry.image_size_px != frames.shape[1]:
        raise DatasetError(
            f"{path}: attribute 'geometry' says image_size_px={geometry.image_size_px} but "
            f"frames are {frames.shape[1]} px"
        )
    force = load(("force",), "(N,) force", (n,)).astype(np.float64)
    return {
        "force_n": force_to_newtons(force, _text(unit)),
        "position_mm": load(("position",), "(N, 2) float64 mm", (n, 2)).astype(np.float64),
        "valid": load(("valid",), "(N,) bool", (n,)).astype(bool),
        "timestamp_s": load(("timestamp",), "(N,) float64 unix seconds", (n,)).astype(np.float64),
        "channel_order": channel_order,
        "geometry": geometry,
        "fps": float(f.attrs.get("fps", 30.0)),
        "provenance": _attr_json(f, "provenance", {}),
        "pixel_mean": f.attrs.get("pixel_mean"),
        "pixel_std": f.attrs.get("pixel_std"),
    }


def dataset_fingerprint(ds: Dataset) -> str:
    """A short hash identifying a dataset's content: shapes, all per-frame labels
    (force, position, validity) and a few frames. Cheap even for 20 GB files."""
    h = hashlib.sha256()
    h.update(repr((tuple(ds.frames.shape), ds.channel_order, ds.geometry.to_json())).encode())
    for arr in (ds.force_n, ds.position_mm, ds.valid):
        h.update(np.ascontiguousarray(arr).tobytes())
    n = len(ds)
    for i in np.unique(np.linspace(0, n - 1, min(n, FINGERPRINT_SAMPLE_FRAMES)).astype(int)):
        h.update(np.ascontiguousarray(ds.frames[int(i)]).tobytes())
    return h.hexdigest()[:16]
