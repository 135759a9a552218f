"""Recording live readings to a file (HDF5 readings file or MCAP) on a thread of its own."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from beadsight.errors import BeadSightError
from beadsight.live.listeners import LiveStatus, LiveUpdate, UpdateQueue

logger = logging.getLogger(__name__)

RECORDER_QUEUE_SIZE = 3000  # ~100 s at 30 Hz of readings waiting for the disk


class Recorder:
    """Writes updates to a ReadingsWriter / McapReadingsWriter on its own thread."""

    def __init__(self, writer: Any, maxsize: int = RECORDER_QUEUE_SIZE):
        self.writer = writer
        self.path = Path(writer.path)
        self.queue = UpdateQueue(maxsize)
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="beadsight-recorder", daemon=True)
        self._thread.start()

    # listener interface: only queue
    def push(self, update: LiveUpdate) -> None:
        self.queue.push(update)

    def status(self, status: LiveStatus) -> None:
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
        except BaseException as e:  # disk full, bad path: report, keep the partial file
            self.error = e
            logger.error("recording to %s failed: %s", self.path, e)
            self.writer.abort()

    @property
    def count(self) -> int:
        return len(self.writer)

    def close(self) -> Path:
        self.queue.finish()
        self._thread.join()
        if self.error is not None:
            raise BeadSightError(f"{self.path}: recording failed: {self.error}") from self.error
        if self.queue.dropped:
            logger.warning(
                "%s: %d readings were dropped (disk too slow)", self.path, self.queue.dropped
            )
        return self.path


def open_recording_writer(path: str | Path, geometry, provenance: dict[str, Any]) -> Any:
    """A writer for ``path`` by suffix: ``.h5``/``.hdf5`` readings file or ``.mcap``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        from beadsight.live.readings import ReadingsWriter

        return ReadingsWriter(path, geometry, provenance)
    if suffix == ".mcap":
        from beadsight.live.mcap import McapReadingsWriter

        return McapReadingsWriter(path, geometry, provenance)
    raise ValueError(f"{path}: recording format unknown; use a .h5 or .mcap file name")
