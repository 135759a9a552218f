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
  :data:`~beadsight.live.recording.partial.DISK_RESERVE_BYTES` are still free, enough to close the file properly. They then
  raise :class:`~beadsight.files.WriteError` ("disk full") naming the file; everything
  written before stays readable in ``NAME.partial`` (an empty one is removed). A write
  that fails anyway (another program filled the disk meanwhile) raises the same error.
* **Writing never slows sensing.** :class:`Recorder` is a live listener that queues updates
  and writes them on its own thread; a failure ends the recording, not the sensing.
* **Health with the readings.** The recorder hands the writer a health report (the sensor's
  state and drift health, :func:`~beadsight.live.ros.messages.health_report`, stamped with
  the reading's capture time) whenever either state changes, else once every
  :data:`~beadsight.live.config.HEALTH_PERIOD_S` of capture time (MCAP keeps it).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from beadsight.errors import BeadSightError, ConfigError
from beadsight.live.config import HEALTH_PERIOD_S
from beadsight.live.recording.mcap import McapReadingsWriter
from beadsight.live.recording.partial import (
    PartialWriter,
)
from beadsight.live.recording.readings import ReadingsWriter
from beadsight.live.ros.messages import health_report

logger = logging.getLogger(__name__)

RECORDER_QUEUE_SIZE = 3000  # ~100 s at 30 Hz of readings waiting for the disk


def open_recording_writer(
    path: str | Path, geometry, provenance: dict[str, Any], overwrite: bool = False
) -> PartialWriter:
    """A writer for ``path`` by suffix: ``.h5``/``.hdf5`` readings file or ``.mcap``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return ReadingsWriter(path, geometry, provenance, overwrite=overwrite)
    if suffix == ".mcap":
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
        self._status: Any = None  # the sensor's newest LiveStatus
        self._health_key: tuple | None = None  # (sensor state, health state) last recorded
        self._health_due = -float("inf")  # capture time (s) of the next periodic report
        self._thread = threading.Thread(target=self._run, name="beadsight-recorder", daemon=True)
        self._thread.start()

    # listener interface: only queue
    def push(self, update: Any) -> None:
        if self.error is None:  # with the sensor's state as the reading was made
            self.queue.push((update, self._status))

    def status(self, status: Any) -> None:
        self._status = status  # (sensing thread) goes with the next readings

    def _health(self, update: Any, status: Any) -> dict[str, Any] | None:
        """The health report to record with ``update``, or None (nothing new, not due)."""
        health = getattr(update, "health", None)
        key = (getattr(status, "state", None), getattr(health, "state", None))
        t = float(update.reading.timestamp_s)
        if key == self._health_key and t < self._health_due:
            return None
        self._health_key, self._health_due = key, t + HEALTH_PERIOD_S
        return health_report(status, health, t)

    def finish(self) -> None:
        self.queue.finish()

    def _run(self) -> None:
        try:
            while True:
                try:
                    item = self.queue.get()
                except EOFError:
                    break
                if item is not None:
                    update, status = item
                    # recorded under the frame's index in the source (a replayed
                    # dataset's row), not the predictor's count of frames it was given
                    reading = dataclasses.replace(update.reading, frame_index=update.source_index)
                    self.writer.append(
                        reading,
                        reference_force_n=update.reference_force_n,
                        latency_s=update.latency_s,
                        health=self._health(update, status),
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
