"""Append rows to an HDF5 file written as ``NAME.partial`` and renamed when finished:
the writer of ``predictions.h5`` (``beadsight predict`` and ``beadsight evaluate``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

import h5py
import numpy as np

from beadsight.files import (
    WriteError,
    describe_write_failure,
    finish_partial,
    free_bytes,
    partial_path,
)

log = logging.getLogger(__name__)

H5_COMPRESSION = "gzip"
H5_COMPRESSION_LEVEL = 1  # gzip level: ~2x faster than 4 on float maps, ~5 % larger
H5_WRITE_ERRORS = (OSError, RuntimeError)  # what h5py raises when a write fails (disk full)
H5_SMALL_CHUNK_ROWS = 1024  # rows per chunk of uncompressed (per-frame scalar) datasets
H5_DISK_RESERVE_BYTES = 64 * 1024  # left free by each append, so that HDF5 can close the file


class IncrementalH5:
    """Append rows to resizable HDF5 datasets in ``<path>.partial``; rename on finish.

    specs: {name: (row_shape, dtype, compress)}; compressed datasets use gzip with
    one row per chunk. Use as a context manager: an exception (in the block or while
    finishing) deletes the partial file and leaves any existing ``path`` untouched; a
    damaged file is never renamed to ``path``.

    A full disk raises :class:`~beadsight.files.WriteError` naming the file. HDF5 cannot
    recover from a write that fails half-way (it can crash when the file is closed), so
    each append first checks that the disk has room for every chunk it touches,
    uncompressed, plus :data:`H5_DISK_RESERVE_BYTES`, and is flushed; a write that fails anyway (another
    program filled the disk meanwhile) raises the same error.
    """

    def __init__(self, path: str | Path, specs: dict[str, tuple[tuple[int, ...], object, bool]]):
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.file: h5py.File | None = None
        self.rows = 0
        self._failed = False  # a write failed: the file's content is damaged
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.file = h5py.File(self.partial, "w")
            for name, (row_shape, dtype, compress) in specs.items():
                chunk_rows = 1 if compress else H5_SMALL_CHUNK_ROWS
                ds = self.file.create_dataset(
                    name,
                    (0, *row_shape),
                    dtype=dtype,
                    maxshape=(None, *row_shape),
                    chunks=(chunk_rows, *row_shape),
                    compression=H5_COMPRESSION if compress else None,
                    compression_opts=H5_COMPRESSION_LEVEL if compress else None,
                )
                ds.attrs["row_shape"] = json.dumps(list(row_shape))
            self.file.flush()
        except H5_WRITE_ERRORS as e:
            self._failed = True
            self.abort()
            raise self._write_error(e) from e

    def _write_error(self, e: BaseException) -> WriteError:
        return WriteError(
            f"could not write {self.path} (written as {self.partial.name}, removed): "
            f"{describe_write_failure(e)}"
        )

    def _bytes_needed(self, n: int) -> int:
        """At most the bytes appending ``n`` rows writes: every chunk it touches, in full
        (HDF5 allocates whole chunks), with room for gzip's worst case on compressed ones."""
        total = 0
        for ds in self.file.values():
            rows = ds.chunks[0]
            touched = -(-(self.rows + n) // rows) - self.rows // rows
            chunk_bytes = ds.dtype.itemsize * int(np.prod(ds.chunks))
            total += touched * (chunk_bytes + (chunk_bytes // 100 + 64 if ds.compression else 0))
        return total

    def append(self, **columns: np.ndarray) -> None:
        """Append n rows; every dataset must receive the same number of rows."""
        lengths = {len(v) for v in columns.values()}
        if len(lengths) != 1 or set(columns) != set(self.file.keys()):
            raise ValueError(f"append needs one row count for all of {sorted(self.file.keys())}")
        n = lengths.pop()
        need = self._bytes_needed(n) + H5_DISK_RESERVE_BYTES
        free = free_bytes(self.partial.parent)
        if free < need:
            raise WriteError(
                f"could not write {self.path} (written as {self.partial.name}, removed): "
                f"disk full ({free} bytes free, the next {n} rows need up to {need})"
            )
        try:
            for name, values in columns.items():
                ds = self.file[name]
                ds.resize(self.rows + n, axis=0)
                ds[self.rows :] = values
            self.file.flush()
        except H5_WRITE_ERRORS as e:
            self._failed = True
            raise self._write_error(e) from e
        self.rows += n

    def finish(self) -> Path:
        """Close the file and rename it to ``path``; on failure remove it (WriteError)."""
        try:
            self.file.flush()
            self.file.close()
        except H5_WRITE_ERRORS as e:
            self._failed = True
            self.abort()
            raise self._write_error(e) from e
        return finish_partial(self.partial, self.path)

    def abort(self) -> None:
        """Close and delete the partial file (never raises)."""
        if self.file is not None and self.file.id.valid:
            if self._failed:  # free the disk, so that HDF5 has room to close the file
                with contextlib.suppress(OSError):
                    os.truncate(self.partial, 0)
            try:
                self.file.close()
            except H5_WRITE_ERRORS as e:  # pragma: no cover - HDF5 could not even close
                log.warning("%s: could not close the partial file: %s", self.partial, e)
        self.partial.unlink(missing_ok=True)

    def __enter__(self) -> IncrementalH5:
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        if exc_type is not None:
            self.abort()
            return
        try:
            self.finish()
        except BaseException:
            self.abort()
            raise
