"""Writing a dataset (HDF5) incrementally, safe against crashes and full disks.

See :class:`DatasetWriter`; the layout is :mod:`beadsight.data.dataset`'s.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import h5py
import numpy as np

from beadsight import __version__
from beadsight.config import ContactThresholds, SensorGeometry
from beadsight.data.dataset import FORMAT, FORMAT_VERSION, DatasetError
from beadsight.data.presses import segment_presses
from beadsight.files import (
    ClosesOrAborts,
    WriteError,
    describe_write_failure,
    finish_partial,
    os_errors_as_write_errors,
    partial_path,
)

SPACE_MARGIN_BYTES = 1 << 20  # free disk kept for HDF5's own allocations while writing
ROW_BYTES = 8 + 16 + 1 + 8 + 1 + 4  # force, position, valid, timestamp, contact, press_id


class DatasetWriter(ClosesOrAborts):
    """Write a dataset incrementally; safe against crashes mid-write and full disks.

    Data goes to ``<path>.partial`` (flushed after every :meth:`append`, so what
    was appended stays readable after a crash); :meth:`close` adds the press
    segmentation and pixel statistics and renames the file to ``path``. A write
    that fails (disk full, quota, file size limit) raises
    :class:`~beadsight.files.WriteError` naming the file and the cause; the file is
    then never renamed to ``path`` (what was written stays in ``<path>.partial``).

    Usage::

        with DatasetWriter(path, geometry, fps=30, provenance={...}) as w:
            w.append(frames_rgb, force_n, position_mm, valid, timestamp_s)
    """

    def __init__(
        self,
        path: str | Path,
        geometry: SensorGeometry,
        *,
        channel_order: str = "RGB",
        fps: float = 30.0,
        provenance: dict[str, Any] | None = None,
        compression: str | None = None,
        thresholds: ContactThresholds = ContactThresholds(),
    ):
        if channel_order not in ("RGB", "BGR"):
            raise ValueError(f"channel_order must be RGB or BGR, got {channel_order!r}")
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.geometry = geometry
        self.thresholds = thresholds
        self.failed = False
        self.space_margin_bytes = SPACE_MARGIN_BYTES
        attrs = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "fps": float(fps),
            "geometry": geometry.to_json(),
            "thresholds": thresholds.to_json(),
            "provenance": json.dumps(
                {
                    "created_unix": time.time(),
                    "beadsight_version": __version__,
                    **(provenance or {}),
                },
                default=str,
            ),
        }
        with os_errors_as_write_errors(self.partial):
            self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._writing():
            self._f = h5py.File(self.partial, "w")
            self._f.attrs.update(attrs)
            self._create_datasets(channel_order, compression)
        self._sum = np.zeros(3)
        self._sumsq = np.zeros(3)
        self._count = 0

    def _create_datasets(self, channel_order: str, compression: str | None) -> None:
        # The handles stay open until close(): HDF5 reports a failed write of a dataset's
        # cached chunks when the file is flushed, but only as an ignored error when the
        # dataset is closed, so a handle dropped after each append could lose data silently.
        s = self.geometry.image_size_px
        self._ds: dict[str, h5py.Dataset] = {}
        frames = self._ds["frames"] = self._f.create_dataset(
            "frames",
            (0, s, s, 3),
            np.uint8,
            maxshape=(None, s, s, 3),
            chunks=(1, s, s, 3),
            compression=compression,
        )
        frames.attrs["channel_order"] = channel_order
        spec = {
            "force": ((), np.float64, "N"),
            "position": ((2,), np.float64, "mm"),
            "valid": ((), bool, ""),
            "timestamp": ((), np.float64, "s (unix)"),
        }
        for name, (shape, dtype, unit) in spec.items():
            ds = self._ds[name] = self._f.create_dataset(
                name, (0, *shape), dtype, maxshape=(None, *shape), chunks=(4096, *shape)
            )
            if unit:
                ds.attrs["unit"] = unit

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """HDF5 write errors (h5py raises OSError or RuntimeError) -> WriteError; the file
        is marked failed so that :meth:`close` never renames it into place.

        The WriteError is raised outside the ``except`` block, so that it does not keep
        the h5py error (and the HDF5 objects its traceback holds) alive: freeing those
        after the failed file is closed crashes HDF5.
        """
        try:
            yield
            return
        except (OSError, RuntimeError) as e:
            self.failed = True
            cause = describe_write_failure(e)
        self.abort()
        raise WriteError(
            f"could not write {self.partial}: {cause}; {self.path} was not written (what was "
            f"written so far stays in {self.partial.name})"
        )

    def _check_space(self, nbytes: int) -> None:
        """Refuse a write the disk has no room for, before HDF5 tries it.

        HDF5 (2.0) can crash the process when it closes a file after a failed write, so a
        full disk is caught here while the file is still intact: it is closed cleanly and
        stays readable as ``.partial``. ``space_margin_bytes`` is kept free for HDF5's own
        allocations (chunk growth, metadata written at close). Another program filling the
        disk between this check and the write still fails in HDF5 (see :meth:`_writing`).
        """
        free = shutil.disk_usage(self.partial.parent).free
        if free >= nbytes + self.space_margin_bytes:
            return
        self.failed = True
        self.abort()
        raise WriteError(
            f"could not write {self.partial}: disk full ({free} bytes free; the next write "
            f"needs {nbytes} bytes plus {self.space_margin_bytes} kept free); {self.path} was "
            f"not written (what was written so far stays readable in {self.partial.name})"
        )

    def __len__(self) -> int:
        return int(self._ds["force"].shape[0])

    def append(self, frames, force_n, position_mm, valid, timestamp_s) -> None:
        """frames: (n, S, S, 3) uint8; force_n: (n,) N; position_mm: (n, 2); valid: (n,) bool;
        timestamp_s: (n,) float64 unix seconds."""
        frames = np.asarray(frames)
        n = len(frames)
        s = self.geometry.image_size_px
        if frames.shape[1:] != (s, s, 3) or frames.dtype != np.uint8:
            raise DatasetError(
                f"{self.path}: frames must be (n, {s}, {s}, 3) uint8, got {frames.shape} {frames.dtype}"
            )
        if self.failed:
            raise WriteError(f"{self.partial}: an earlier write failed; nothing more is written")
        self._check_space(frames.nbytes + n * ROW_BYTES)
        cols = {
            "force": np.asarray(force_n, np.float64).reshape(n),
            "position": np.asarray(position_mm, np.float64).reshape(n, 2),
            "valid": np.asarray(valid, bool).reshape(n),
            "timestamp": np.asarray(timestamp_s, np.float64).reshape(n),
        }
        with self._writing():
            start = len(self)
            for name, values in {"frames": frames, **cols}.items():
                self._ds[name].resize(start + n, axis=0)  # no local h5py handle (see _writing)
                self._ds[name][start:] = values
            self._f.flush()
        pixels_per_frame = frames.shape[1] * frames.shape[2]
        for frame in frames:  # cv2 avoids a float64 copy of the batch (~0.1 ms per frame)
            mean, std = (v.ravel() for v in cv2.meanStdDev(frame))
            self._sum += mean * pixels_per_frame
            self._sumsq += (std * std + mean * mean) * pixels_per_frame
        self._count += n * pixels_per_frame

    def close(self) -> Path:
        """Finish the file (presses, pixel stats) and move it into place. Returns the path.

        After a failed write, only releases the file (raising WriteError): a damaged
        file is never renamed to ``path``.
        """
        if not self._f.id.valid:
            if self.failed:
                raise WriteError(f"{self.partial}: a write failed; {self.path} was not written")
            return self.path
        if self.failed:
            self.abort()
            raise WriteError(f"{self.partial}: a write failed; {self.path} was not written")
        f = self._f
        self._check_space(len(self) * ROW_BYTES)
        with self._writing():
            force, valid, position = (self._ds[k][()] for k in ("force", "valid", "position"))
            contact, press_id, presses = segment_presses(force, valid, position, self.thresholds)
            f.create_dataset("contact", data=contact)
            f.create_dataset("press_id", data=press_id)
            f.create_dataset("presses", data=presses.reshape(-1, 2))
            if self._count:
                mean = self._sum / self._count
                f.attrs["pixel_mean"] = mean
                f.attrs["pixel_std"] = np.sqrt(np.maximum(self._sumsq / self._count - mean**2, 0.0))
            f.flush()
            self._ds.clear()
            f.close()
        return finish_partial(self.partial, self.path)

    def abort(self) -> None:
        """Close without finishing; the ``.partial`` file stays for inspection.

        After a failed write, HDF5 repeats the failure while closing each dataset; those
        repeats (already raised as WriteError) are not printed again.
        """
        f = getattr(self, "_f", None)
        if f is None or not f.id.valid:
            return
        hook = sys.unraisablehook
        if self.failed:
            sys.unraisablehook = lambda u: None if _is_write_failure(u.exc_value) else hook(u)
        try:
            getattr(self, "_ds", {}).clear()
            f.close()
        except (OSError, RuntimeError):  # a file that already failed to write
            self.failed = True
        finally:
            sys.unraisablehook = hook


def _is_write_failure(e: BaseException | None) -> bool:
    return isinstance(e, (OSError, RuntimeError)) and "write failed" in str(e)
