"""The rules every recording of live readings follows, whatever its format: the target
checks and :class:`PartialWriter`, the base of the HDF5 and MCAP writers (the rules themselves
are in :mod:`beadsight.live.recording.recorder`'s docstring and docs/live.md)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.files import (
    ClosesOrAborts,
    OutputExistsError,
    WriteError,
    describe_write_failure,
    finish_partial,
    free_bytes,
    os_errors_as_write_errors,
    partial_path,
    refuse_existing,
)

logger = logging.getLogger(__name__)

RECORD_NAME = "beadsight-%Y%m%d-%H%M%S"  # time.strftime pattern of the Record button's files
DISK_RESERVE_BYTES = 64 * 1024  # left free by a recording, so that it can always close its file


def check_recording_target(path: Path, overwrite: bool) -> Path:
    """Refuse ``path`` if it (or its ``.partial``) exists and not ``overwrite``; return the
    ``.partial`` path the recording is written to."""
    partial = partial_path(path)
    refuse_existing(path, overwrite)
    if (partial.exists() or partial.is_symlink()) and not overwrite:
        raise OutputExistsError(
            f"{partial}: exists (left by a recording that did not finish?); move it away, or "
            "pass --overwrite to replace it"
        )
    return partial


def unique_recording_path(folder: str | Path, suffix: str = ".h5") -> Path:
    """A new file name in ``folder`` from the current time: ``beadsight-YYYYmmdd-HHMMSS.h5``,
    then ``...-2.h5``, ``...-3.h5`` if that name (or its ``.partial``) is taken."""
    folder = Path(folder)
    stem = time.strftime(RECORD_NAME)
    for n in range(1, 10_000):
        path = folder / (f"{stem}{suffix}" if n == 1 else f"{stem}-{n}{suffix}")
        if not (path.exists() or partial_path(path).exists()):
            return path
    raise OutputExistsError(f"{folder}: no free name for a recording starting {stem}")


class ReadingLike(Protocol):
    """What a recorder needs from a reading (``beadsight.inference.predictor.PressureReading`` has it)."""

    pressure_kpa: np.ndarray
    force_n: float
    cop_mm: np.ndarray
    has_contact: bool
    contact_area_mm2: float
    timestamp_s: float
    latency_s: float
    frame_index: int


class PartialWriter(ClosesOrAborts):
    """Base of the recording writers: the ``.partial`` file, refusing to replace files, and
    the clean stop on a full disk. Not thread-safe: call it from one thread.

    ``writer(path, geometry, provenance, overwrite=...)`` calls :meth:`_prepare` (set up the
    writer's own state; may refuse, e.g. a missing package), refuses an existing ``path``,
    then :meth:`_create` (create ``self.partial``, exclusively unless ``self.overwrite``, and
    set ``self._created``). :meth:`append` counts each reading that :meth:`_add` took; a
    subclass adds to ``self._written`` the readings that reached the file and implements
    :meth:`_close_file` (close the file, first writing what is buffered if ``flush``; may
    raise). ``len(writer)`` counts the readings appended.
    """

    def __init__(
        self,
        path: str | Path,
        geometry: SensorGeometry,
        provenance: dict[str, Any] | None = None,
        *,
        overwrite: bool = False,
    ):
        self.geometry = geometry
        self._prepare()
        self.path = Path(path)
        self.overwrite = overwrite
        self.partial = check_recording_target(self.path, overwrite)
        self._error: WriteError | None = None
        self._closed = False
        self._count = 0  # readings appended
        self._written = 0  # readings in the file
        self._created = False  # this writer created self.partial
        with os_errors_as_write_errors(self.partial):
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._guard(lambda: self._start(provenance))

    def _start(self, provenance: dict[str, Any] | None) -> None:
        """:meth:`_create`; a ``.partial`` that a failing create left (an empty file on a
        full disk) counts as created, so that the failure removes it."""
        existed = self.partial.exists() or self.partial.is_symlink()
        try:
            self._create(provenance)
        finally:
            self._created = self._created or (not existed and self.partial.exists())

    def _prepare(self) -> None:
        """The writer's own state, before the file is created."""

    def _create(self, provenance: dict[str, Any] | None) -> None:
        raise NotImplementedError

    def append(
        self,
        reading: ReadingLike,
        reference_force_n: float = math.nan,
        latency_s: float | None = None,
        health: dict[str, Any] | None = None,
    ) -> None:
        """Record one reading: ``reference_force_n`` is the true force, N (NaN: unknown),
        ``latency_s`` capture -> reading available (default: ``reading.latency_s``),
        ``health`` a :func:`~beadsight.live.ros.messages.health_report` to record with it
        (None: none now; the recorder hands one on each change and once a second).

        Raises :class:`~beadsight.files.WriteError` once the disk is full.
        """
        self._check_open()
        self._add(reading, reference_force_n, latency_s, health)
        self._count += 1
        self._after_add()

    def _add(
        self,
        reading: ReadingLike,
        reference_force_n: float,
        latency_s: float | None,
        health: dict[str, Any] | None,
    ) -> None:
        """Buffer or write one reading (``self._count`` readings came before it)."""
        raise NotImplementedError

    def _after_add(self) -> None:
        """After the reading was counted: e.g. write a full buffer."""

    def _disk_full(self, room: int, what: str) -> None:
        """Stop cleanly: ``room`` (bytes, :meth:`_room`) is too little for ``what``."""
        free_kib = (max(room, 0) + DISK_RESERVE_BYTES) // 1024
        self._fail(f"disk full ({free_kib} KiB free, too little for {what})")

    def __len__(self) -> int:
        return self._count

    @property
    def error(self) -> WriteError | None:
        """The failure that stopped this recording, if one did."""
        return self._error

    def _close_file(self, flush: bool) -> None:
        raise NotImplementedError

    def _room(self) -> int:
        """Bytes the recording may still write, keeping :data:`DISK_RESERVE_BYTES` free."""
        return free_bytes(self.partial.parent) - DISK_RESERVE_BYTES

    def _check_open(self) -> None:
        if self._error is not None:
            raise self._error
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")

    def _fail(self, cause: str, clean: bool = True) -> None:
        """Stop recording: close the file, keep what was written, raise a named WriteError.

        clean: the file was closed normally (stopped before the disk was full), so every
        reading in it is readable; otherwise a write failed half-way.
        """
        if not self._closed:
            self._closed = True
            try:
                self._close_file(flush=False)
            except Exception as e:  # the library may be in a bad state after a failed write
                clean = False
                logger.debug("%s: closing after a failed write: %s", self.partial, e)
        if self._written == 0:
            if self._created:
                self.partial.unlink(missing_ok=True)
            kept = "nothing was recorded"
        else:
            kept = f"the {self._written} readings before it are in {self.partial}"
            if not clean:
                kept += " (the end of the file may be damaged)"
        self._error = WriteError(f"could not write {self.path}: {cause}; {kept}")
        raise self._error

    def _guard(self, write: Callable[[], Any]) -> Any:
        """Run ``write()``; a failure of the file or its library stops the recording."""
        try:
            return write()
        except (OSError, RuntimeError) as e:
            self._fail(describe_write_failure(e), clean=False)

    def close(self) -> Path:
        """Write what is buffered, close, and rename ``NAME.partial`` to ``NAME``.

        Raises the :class:`WriteError` that stopped the recording, if one did.
        """
        if self._error is not None:
            raise self._error
        if not self._closed:
            self._guard(lambda: self._close_file(flush=True))
            self._closed = True
            if not self.overwrite and self.path.exists():
                raise OutputExistsError(
                    f"{self.path}: appeared while recording; the recording is in {self.partial}"
                )
            finish_partial(self.partial, self.path)
            logger.info("wrote %d readings to %s", self._written, self.path)
        return self.path

    def abort(self) -> None:
        """Close without renaming: ``NAME.partial`` keeps what was written."""
        if not self._closed and self._error is None:
            try:
                self._guard(lambda: self._close_file(flush=True))
            except WriteError as e:
                logger.error("%s", e)
                return
            self._closed = True
            if self._written == 0 and self._created:
                self.partial.unlink(missing_ok=True)
