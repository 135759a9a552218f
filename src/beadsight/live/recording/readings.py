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
file at ``path`` is always complete; after a crash or a full disk the ``.partial`` file
holds what was flushed (see :mod:`beadsight.live.recording.recorder`).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from beadsight import __version__
from beadsight.config import SensorGeometry
from beadsight.errors import BeadSightError
from beadsight.files import Closes
from beadsight.h5safe import find_dataset, open_h5
from beadsight.live.recording.partial import PartialWriter, ReadingLike

logger = logging.getLogger(__name__)

FORMAT = "beadsight-readings"
FORMAT_VERSION = 1
FLUSH_EVERY = 32  # readings buffered in memory between writes to the file
SCALAR_CHUNK_ROWS = 1024  # readings per HDF5 chunk of the scalar datasets
READING_OVERHEAD_BYTES = 512  # most file bytes per reading beyond its raw map (chunk index)
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


class ReadingsWriter(PartialWriter):
    """Append readings to an HDF5 file; ``with ReadingsWriter(path, geometry) as w: w.append(r)``.

    Readings are buffered and written every :data:`FLUSH_EVERY` readings (then flushed),
    so appending costs microseconds; :meth:`close` writes the rest and moves the file
    into place. An existing ``path`` is refused unless ``overwrite``. A full disk stops
    the recording with a :class:`~beadsight.files.WriteError` (see
    :mod:`beadsight.live.recording.recorder`). Not thread-safe: call it from one thread.
    """

    def _prepare(self) -> None:
        s = self.geometry.image_size_px
        self._map_bytes = s * s * np.dtype(np.float32).itemsize + READING_OVERHEAD_BYTES
        self._scalar_chunk_bytes = sum(
            SCALAR_CHUNK_ROWS * np.dtype(dtype).itemsize * int(np.prod(shape))
            for shape, dtype, _unit in SCALAR_FIELDS.values()
        )
        self._rows: list[dict[str, Any]] = []
        self._maps: list[np.ndarray] = []
        self._f: h5py.File | None = None

    def _create(self, provenance: dict[str, Any] | None) -> None:
        # no chunk cache: every write reaches the file at once, so a failure raises here
        self._f = h5py.File(self.partial, "w" if self.overwrite else "w-", rdcc_nbytes=0)
        self._created = True
        s = self.geometry.image_size_px
        self._f.attrs.update(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "geometry": self.geometry.to_json(),
                "provenance": json.dumps(
                    {"created_unix": time.time(), "beadsight_version": __version__}
                    | (provenance or {}),
                    default=str,
                ),
            }
        )
        self._ds: dict[str, h5py.Dataset] = {}
        for name, (shape, dtype, unit) in SCALAR_FIELDS.items():
            self._ds[name] = self._f.create_dataset(
                name,
                (0, *shape),
                dtype,
                maxshape=(None, *shape),
                chunks=(SCALAR_CHUNK_ROWS, *shape),
            )
            if unit:
                self._ds[name].attrs["unit"] = unit
        self._ds["pressure_kpa"] = self._f.create_dataset(
            "pressure_kpa",
            (0, s, s),
            np.float32,
            maxshape=(None, s, s),
            chunks=(1, s, s),
            compression=MAP_COMPRESSION,
        )
        self._ds["pressure_kpa"].attrs["unit"] = "kPa"
        self._f.flush()

    def _add(
        self,
        reading: ReadingLike,
        reference_force_n: float,
        latency_s: float | None,
        health: dict[str, Any] | None,
    ) -> None:
        """Buffer one reading; ``reading.pressure_kpa`` must be (S, S) with S = geometry size.
        (``health`` is not kept: this format has no health; MCAP recordings keep it.)"""
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

    def _after_add(self) -> None:
        if len(self._rows) >= FLUSH_EVERY:
            self._write_buffer()

    def _bytes_for(self, n: int) -> int:
        """Most bytes that writing the next ``n`` readings adds to the file."""
        start, rows = self._written, SCALAR_CHUNK_ROWS
        new_chunks = -(-(start + n) // rows) - (-(-start // rows))
        return n * self._map_bytes + new_chunks * self._scalar_chunk_bytes

    def _write_buffer(self) -> None:
        n = len(self._rows)
        if n == 0:
            return
        room = self._room()
        fit = next((k for k in range(n, 0, -1) if self._bytes_for(k) <= room), 0)
        if fit:
            self._guard(lambda: self._write_rows(fit))
            self._written += fit
        self._rows.clear()
        self._maps.clear()
        if fit < n:
            self._disk_full(room, "the next readings")

    def _write_rows(self, n: int) -> None:
        start = self._written
        try:
            for name, (shape, dtype, _unit) in SCALAR_FIELDS.items():
                rows = self._rows[:n]
                values = np.asarray([row[name] for row in rows], dtype=dtype).reshape(n, *shape)
                self._ds[name].resize(start + n, axis=0)
                self._ds[name][start:] = values
            self._ds["pressure_kpa"].resize(start + n, axis=0)
            self._ds["pressure_kpa"][start:] = np.stack(self._maps[:n])
            self._f.flush()
        except BaseException:
            # rows whose data did not reach the file must not read back as (zero) readings
            for ds in self._ds.values():
                try:
                    ds.resize(start, axis=0)
                except Exception:  # noqa: S110 - best effort after a failed write
                    pass
            raise

    def _close_file(self, flush: bool) -> None:
        if self._f is None:
            return
        try:
            if flush:
                self._write_buffer()
        finally:
            if self._f is not None:  # (a failed flush has closed it already)
                f, self._f, self._ds = self._f, None, {}
                f.close()


@dataclass
class ReadingsFile(Closes):
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
        bad = np.flatnonzero(~np.isfinite(columns["timestamp_s"]))
        if bad.size:
            raise ReadingsFileError(
                f"{path}: dataset 'timestamp_s' has {bad.size} NaN/inf value(s) (first at "
                f"reading {bad[0]}); expected finite seconds"
            )
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
