"""Recording live readings to files: what ``beadsight live --output`` and the viewer's Record
button share, whatever the format (HDF5 readings file, MCAP).

* **Never a damaged file under its final name.** A recording is written to ``NAME.partial``
  and renamed to ``NAME`` only after its last write succeeded (:mod:`beadsight.files`).
* **Never a silent overwrite.** An existing ``NAME`` (or a ``NAME.partial`` left by an
  earlier recording) is refused unless ``overwrite``; the viewer picks a new name
  (:func:`unique_recording_path`).
* **A full disk stops the recording cleanly.** HDF5 cannot recover from a write that fails
  half-way (the file can be left unreadable, the library can crash at exit), so the
  writers check the free space before each write and stop while
  :data:`DISK_RESERVE_BYTES` are still free, enough to close the file properly. They then
  raise :class:`~beadsight.files.WriteError` ("disk full") naming the file; everything
  written before stays readable in ``NAME.partial`` (an empty one is removed). A write
  that fails anyway (another program filled the disk meanwhile) raises the same error.
* **Writing never slows sensing.** :class:`Recorder` is a live listener that queues updates
  and writes them on its own thread; a failure ends the recording, not the sensing.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.errors import BeadSightError, ConfigError
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

DISK_RESERVE_BYTES = 64 * 1024  # left free by a recording, so that it can always close its file
RECORDER_QUEUE_SIZE = 3000  # ~100 s at 30 Hz of readings waiting for the disk
RECORD_NAME = "beadsight-%Y%m%d-%H%M%S"  # time.strftime pattern of the Record button's files


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
    ) -> None:
        """Record one reading: ``reference_force_n`` is the true force, N (NaN: unknown),
        ``latency_s`` capture -> reading available (default: ``reading.latency_s``).

        Raises :class:`~beadsight.files.WriteError` once the disk is full.
        """
        self._check_open()
        self._add(reading, reference_force_n, latency_s)
        self._count += 1
        self._after_add()

    def _add(self, reading: ReadingLike, reference_force_n: float, latency_s: float | None) -> None:
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


def open_recording_writer(
    path: str | Path, geometry, provenance: dict[str, Any], overwrite: bool = False
) -> PartialWriter:
    """A writer for ``path`` by suffix: ``.h5``/``.hdf5`` readings file or ``.mcap``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        from beadsight.live.readings import ReadingsWriter

        return ReadingsWriter(path, geometry, provenance, overwrite=overwrite)
    if suffix == ".mcap":
        from beadsight.live.mcap import McapReadingsWriter

        return McapReadingsWriter(path, geometry, provenance, overwrite=overwrite)
    raise ConfigError(f"{path}: recording format unknown; use a .h5 or .mcap file name")


class Recorder:
    """A live listener that writes every update with ``writer`` on its own thread.

    A write failure (disk full, ...) ends the recording: the writer keeps what it wrote,
    later updates are ignored, ``on_error(error)`` is called on the recorder's thread, and
    :meth:`close` raises the error.
    """

    def __init__(
        self,
        writer: PartialWriter,
        on_error: Callable[[BaseException], None] | None = None,
        maxsize: int = RECORDER_QUEUE_SIZE,
    ):
        from beadsight.live.listeners import UpdateQueue

        self.writer = writer
        self.path = Path(writer.path)
        self.queue = UpdateQueue(maxsize)
        self.error: BaseException | None = None
        self._on_error = on_error
        self._thread = threading.Thread(target=self._run, name="beadsight-recorder", daemon=True)
        self._thread.start()

    # listener interface: only queue
    def push(self, update: Any) -> None:
        if self.error is None:
            self.queue.push(update)

    def status(self, status: Any) -> None:
        pass

    def finish(self) -> None:
        self.queue.finish()

    def _run(self) -> None:
        try:
            while True:
                try:
                    update = self.queue.get()
                except EOFError:
                    break
                if update is not None:
                    self.writer.append(
                        update.reading,
                        reference_force_n=update.reference_force_n,
                        latency_s=update.latency_s,
                    )
            self.writer.close()
        except BaseException as e:  # disk full, file appeared: report, keep the partial file
            if not isinstance(e, BeadSightError):
                e = BeadSightError(f"{self.path}: recording failed: {e}")
            self.error = e
            self.queue.finish()
            logger.error("recording stopped: %s", e)
            self.writer.abort()
            if self._on_error is not None:
                self._on_error(e)

    @property
    def count(self) -> int:
        return len(self.writer)

    def close(self) -> Path:
        """Finish writing, rename the file into place; raise the recording's error if any."""
        self.queue.finish()
        if self._thread is not threading.current_thread():
            self._thread.join()
        if self.error is not None:
            raise self.error
        if self.queue.dropped:
            logger.warning(
                "%s: %d readings were dropped (disk too slow)", self.path, self.queue.dropped
            )
        return self.path


class RecordingSlot:
    """The one recording a live sensor may have at a time, and why the last one stopped.

    add_listener / remove_listener: the sensor's, so the recorder receives readings.
    Thread-safe; a write failure (disk full) ends the recording, not sensing.
    """

    def __init__(
        self,
        add_listener: Callable[[Any], Any],
        remove_listener: Callable[[Any], None],
    ):
        self._add, self._remove = add_listener, remove_listener
        self._lock = threading.Lock()
        self._recorder: Recorder | None = None
        self._failed: Recorder | None = None  # stopped by an error not yet raised

    def start(
        self,
        path: str | Path,
        geometry: Any,
        provenance: dict[str, Any],
        overwrite: bool,
        on_error: Callable[[BaseException], None] | None,
    ) -> Path:
        with self._lock:
            if self._recorder is not None:
                raise BeadSightError(f"already recording to {self._recorder.path}")
            self._failed = None  # its error was reported (error, on_error)
            writer = open_recording_writer(path, geometry, provenance, overwrite)
            recorder = Recorder(writer, lambda e: self._failed_with(recorder, e, on_error))
            self._recorder = recorder
        self._add(recorder)
        logger.info("recording to %s", path)
        return Path(path)

    def _failed_with(
        self, recorder: Recorder, error: BaseException, on_error: Callable | None
    ) -> None:
        self._remove(recorder)
        with self._lock:
            if self._recorder is recorder:
                self._recorder, self._failed = None, recorder
        if on_error is not None:
            on_error(error)

    def stop(self) -> Path | None:
        """Finish the current recording; its path (None if none). Raises the error that
        stopped it (disk full, ...), if one did."""
        with self._lock:
            recorder = self._recorder or self._failed
            self._failed = None
        if recorder is None:
            return None
        self._remove(recorder)
        try:
            return recorder.close()  # `current` reports it until the file is complete
        finally:
            with self._lock:
                if self._recorder is recorder:
                    self._recorder = None

    @property
    def current(self) -> tuple[Path, int] | None:
        recorder = self._recorder
        return None if recorder is None else (recorder.path, recorder.count)

    @property
    def error(self) -> str | None:
        failed = self._failed
        return None if failed is None else str(failed.error)
