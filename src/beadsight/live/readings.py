"""Files of live readings (HDF5): what ``beadsight live --output readings.h5`` and the
viewer's record button write, and what ``beadsight to-mcap`` reads.

Layout (format ``beadsight-readings``, version 1); N readings, maps H x W:

=====================  ==========  ========  =============================================
dataset                shape       dtype     content
=====================  ==========  ========  =============================================
``timestamp_s``        (N,)        float64   capture time of the newest frame, unix s
``frame_index``        (N,)        int64     index of that frame in the source's stream
``force_n``            (N,)        float32   total normal force (integral of the map), N
``cop_mm``             (N, 2)      float32   centre of pressure (x, y), mm from the sensor
                                             centre, printer frame; NaN without pressure
``has_contact``        (N,)        bool      the predictor's contact decision
``contact_area_mm2``   (N,)        float32   area of the contact mask, mm^2
``latency_s``          (N,)        float32   capture -> reading available, s
``reference_force_n``  (N,)        float32   true force when the source knows it (the
                                             simulator), else NaN
``pressure_kpa``       (N, H, W)   float32   pressure maps, kPa (lzf-compressed chunks)
=====================  ==========  ========  =============================================

File attributes: ``format``, ``format_version``, ``geometry`` (SensorGeometry JSON) and
``provenance`` (JSON: checkpoint, source, backend, beadsight version, creation time).
The writer fills ``<path>.partial`` and renames it on :meth:`ReadingsWriter.close`, so a
file at ``path`` is always complete; after a crash the ``.partial`` file holds what was
flushed.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import h5py
import numpy as np

from beadsight import __version__
from beadsight.config import SensorGeometry
from beadsight.errors import BeadSightError
from beadsight.h5safe import find_dataset, open_h5

logger = logging.getLogger(__name__)

FORMAT = "beadsight-readings"
FORMAT_VERSION = 1
FLUSH_EVERY = 32  # readings buffered in memory between writes to the file
MAP_COMPRESSION = "lzf"  # fast enough for 30 maps/s on one core; zeros compress well

# name -> (per-reading shape, dtype, unit)
SCALAR_FIELDS: dict[str, tuple[tuple[int, ...], Any, str]] = {
    "timestamp_s": ((), np.float64, "s (unix)"),
    "frame_index": ((), np.int64, ""),
    "force_n": ((), np.float32, "N"),
    "cop_mm": ((2,), np.float32, "mm (x, y) from the sensor centre, printer frame"),
    "has_contact": ((), bool, ""),
    "contact_area_mm2": ((), np.float32, "mm^2"),
    "latency_s": ((), np.float32, "s"),
    "reference_force_n": ((), np.float32, "N"),
}


class ReadingsFileError(BeadSightError, ValueError):
    """A readings file is missing, malformed or of another format."""


class ReadingLike(Protocol):
    """What a recorder needs from a reading (``beadsight.inference.predictor.Reading`` has it)."""

    pressure_kpa: np.ndarray
    force_n: float
    cop_mm: np.ndarray
    has_contact: bool
    contact_area_mm2: float
    timestamp_s: float
    latency_s: float
    frame_index: int


class ReadingsWriter:
    """Append readings to an HDF5 file; ``with ReadingsWriter(path, geometry) as w: w.append(r)``.

    Readings are buffered and written every :data:`FLUSH_EVERY` readings (then flushed),
    so appending costs microseconds; :meth:`close` writes the rest and moves the file
    into place. Not thread-safe: call it from one thread.
    """

    def __init__(
        self,
        path: str | Path,
        geometry: SensorGeometry,
        provenance: dict[str, Any] | None = None,
    ):
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.geometry = geometry
        s = geometry.image_size_px
        self._f = h5py.File(self.partial, "w")
        self._f.attrs.update(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "geometry": geometry.to_json(),
                "provenance": json.dumps(
                    {"created_unix": time.time(), "beadsight_version": __version__}
                    | (provenance or {}),
                    default=str,
                ),
            }
        )
        for name, (shape, dtype, unit) in SCALAR_FIELDS.items():
            ds = self._f.create_dataset(
                name, (0, *shape), dtype, maxshape=(None, *shape), chunks=(1024, *shape)
            )
            if unit:
                ds.attrs["unit"] = unit
        maps = self._f.create_dataset(
            "pressure_kpa",
            (0, s, s),
            np.float32,
            maxshape=(None, s, s),
            chunks=(1, s, s),
            compression=MAP_COMPRESSION,
        )
        maps.attrs["unit"] = "kPa"
        self._rows: list[dict[str, Any]] = []
        self._maps: list[np.ndarray] = []
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(
        self,
        reading: ReadingLike,
        reference_force_n: float = math.nan,
        latency_s: float | None = None,
    ) -> None:
        """Buffer one reading; ``reading.pressure_kpa`` must be (S, S) with S = geometry size.

        latency_s: capture -> reading available (default: ``reading.latency_s``).
        """
        s = self.geometry.image_size_px
        pressure = np.asarray(reading.pressure_kpa, dtype=np.float32)
        if pressure.shape != (s, s):
            raise ValueError(
                f"{self.path}: pressure_kpa must be ({s}, {s}) for this file, got {pressure.shape}"
            )
        self._rows.append(
            {
                "timestamp_s": reading.timestamp_s,
                "frame_index": reading.frame_index,
                "force_n": reading.force_n,
                "cop_mm": np.asarray(reading.cop_mm, np.float32).reshape(2),
                "has_contact": bool(reading.has_contact),
                "contact_area_mm2": reading.contact_area_mm2,
                "latency_s": reading.latency_s if latency_s is None else latency_s,
                "reference_force_n": reference_force_n,
            }
        )
        self._maps.append(pressure)
        self._count += 1
        if len(self._rows) >= FLUSH_EVERY:
            self._write_buffer()

    def _write_buffer(self) -> None:
        if not self._rows:
            return
        f = self._f
        start, n = int(f["force_n"].shape[0]), len(self._rows)
        for name, (shape, dtype, _unit) in SCALAR_FIELDS.items():
            values = np.asarray([row[name] for row in self._rows], dtype=dtype).reshape(n, *shape)
            f[name].resize(start + n, axis=0)
            f[name][start:] = values
        f["pressure_kpa"].resize(start + n, axis=0)
        f["pressure_kpa"][start:] = np.stack(self._maps)
        self._rows.clear()
        self._maps.clear()
        f.flush()

    def close(self) -> Path:
        """Write what is buffered, close, and rename ``<path>.partial`` to ``path``."""
        if self._f.id.valid:
            self._write_buffer()
            self._f.close()
            os.replace(self.partial, self.path)
            logger.info("wrote %d readings to %s", self._count, self.path)
        return self.path

    def abort(self) -> None:
        """Close without renaming; the ``.partial`` file keeps what was written."""
        if self._f.id.valid:
            self._write_buffer()
            self._f.close()

    def __enter__(self) -> ReadingsWriter:
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


@dataclass
class ReadingsFile:
    """An open readings file: scalar columns as numpy arrays, maps as an h5py dataset.

    ``pressure_kpa`` is read lazily: ``rf.pressure_kpa[i]`` -> (H, W) float32 kPa.
    """

    path: Path
    geometry: SensorGeometry
    provenance: dict[str, Any]
    timestamp_s: np.ndarray
    frame_index: np.ndarray
    force_n: np.ndarray
    cop_mm: np.ndarray
    has_contact: np.ndarray
    contact_area_mm2: np.ndarray
    latency_s: np.ndarray
    reference_force_n: np.ndarray
    pressure_kpa: h5py.Dataset
    _file: h5py.File

    def __len__(self) -> int:
        return len(self.timestamp_s)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> ReadingsFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_readings(path: str | Path) -> ReadingsFile:
    """Open a file written by :class:`ReadingsWriter`; errors name the file and the field."""
    path = Path(path)
    f = open_h5(path, "readings file", ReadingsFileError, missing=FileNotFoundError)
    try:
        fmt = f.attrs.get("format")
        if fmt != FORMAT:
            raise ReadingsFileError(
                f"{path}: attribute 'format' is {fmt!r}, expected {FORMAT!r} (a file written "
                "by `beadsight live --output` or the viewer's record button)"
            )
        version = int(f.attrs.get("format_version", 0))
        if version > FORMAT_VERSION:
            raise ReadingsFileError(
                f"{path}: format_version {version} is newer than this beadsight reads "
                f"({FORMAT_VERSION}); upgrade beadsight"
            )
        if "geometry" not in f.attrs:
            raise ReadingsFileError(f"{path}: attribute 'geometry' is missing")
        geometry = SensorGeometry.from_dict(json.loads(f.attrs["geometry"]))
        columns = {}
        for name in (*SCALAR_FIELDS, "pressure_kpa"):  # every claim checked before any read
            columns[name] = find_dataset(f, (name,), path, ReadingsFileError)
            if columns[name] is None:
                raise ReadingsFileError(f"{path}: dataset {name!r} is missing")
        n = columns["timestamp_s"].shape[0] if columns["timestamp_s"].ndim else 0
        s = geometry.image_size_px
        shapes = {name: (n, *shape) for name, (shape, _dtype, _unit) in SCALAR_FIELDS.items()}
        for name, shape in {**shapes, "pressure_kpa": (n, s, s)}.items():
            if columns[name].shape != shape:
                raise ReadingsFileError(
                    f"{path}: dataset {name!r} has shape {columns[name].shape}, expected {shape}"
                )
        for name in SCALAR_FIELDS:
            columns[name] = columns[name][()]
        provenance = json.loads(f.attrs.get("provenance", "{}"))
    except ReadingsFileError:
        f.close()
        raise
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as e:
        f.close()
        raise ReadingsFileError(
            f"{path}: unreadable readings file ({type(e).__name__}: {e})"
        ) from None
    except BaseException:
        f.close()
        raise
    return ReadingsFile(path=path, geometry=geometry, provenance=provenance, _file=f, **columns)
