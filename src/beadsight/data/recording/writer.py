"""Writing a raw session folder in this project's format, as data arrives.

See ``docs/recording-format.md`` and :mod:`beadsight.data.recording`. Text logs are
appended (a torn last line left by a crash is cut before appending), video goes to
MJPG chunks (:class:`~beadsight.data.recording.avi.MjpgAviWriter`), and at every chunk
boundary everything is flushed and fsync'ed, so a crash loses at most one chunk.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from beadsight import __version__
from beadsight.data.recording import logs
from beadsight.data.recording.avi import MjpgAviWriter
from beadsight.data.recording.text import read_json
from beadsight.files import WriteError, atomic_write_json, describe_os_error, fsync_dir

logger = logging.getLogger(__name__)


def fmt_float(v: float | None) -> str:
    """Full float64 precision (shortest round-trip repr); empty for None/NaN."""
    if v is None:
        return ""
    v = float(v)
    return "" if math.isnan(v) else repr(v)


class _CsvFile:
    """An append-only CSV file; a torn last line left by a crash is cut before appending."""

    def __init__(self, path: Path, header: Sequence[str] | None):
        self.path = path
        exists = path.exists() and path.stat().st_size > 0
        if exists:
            _cut_torn_tail(path)
        self._f: io.TextIOWrapper = open(path, "a", newline="")  # noqa: SIM115
        self.lock = threading.Lock()
        if not exists and header:
            self._f.write(",".join(header) + "\n")

    def write(self, line: str) -> None:
        with self.lock:
            self._f.write(line + "\n")

    def flush(self, fsync: bool) -> None:
        with self.lock:
            self._f.flush()
            if fsync:
                os.fsync(self._f.fileno())

    def close(self) -> None:
        with self.lock:
            if not self._f.closed:
                self._f.close()


def _cut_torn_tail(path: Path) -> None:
    """Truncate ``path`` after its last newline (drops a half-written last line)."""
    with open(path, "rb+") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        block = min(size, 1 << 16)
        f.seek(size - block)
        tail = f.read(block)
        cut = tail.rfind(b"\n")
        if cut != len(tail) - 1:
            new_size = size - block + cut + 1 if cut >= 0 else 0
            f.truncate(new_size)
            logger.warning(
                "%s: cut a torn last line (%d bytes) before appending", path, size - new_size
            )


class RecordingWriter:
    """Write a raw session folder incrementally (thread-safe; see the module docstring).

    ``metadata`` goes into ``session.json`` (written before anything else, then replaced
    atomically on :meth:`update_metadata` / :meth:`close`). Frames go to MJPG chunks of
    ``chunk_frames`` frames; at every chunk boundary the chunk is closed and all
    files are flushed and fsync'ed. ``resume=True`` appends to an existing session
    (new chunks continue the numbering).

    Any OSError while writing (disk full, file size limit) is raised as
    :class:`RecordingError` naming the file; what was flushed before stays readable.
    """

    def __init__(
        self,
        path: str | Path,
        metadata: dict[str, Any],
        *,
        frame_hw: tuple[int, int],
        fps: float,
        chunk_frames: int | None = None,
        resume: bool = False,
        jpeg_quality: int = logs.JPEG_QUALITY,
    ):
        self.path = Path(path)
        self.jpeg_quality = int(jpeg_quality)
        self.frame_hw = (int(frame_hw[0]), int(frame_hw[1]))
        self.fps = float(fps)
        self.chunk_frames = int(chunk_frames or max(1, round(self.fps)))
        self._lock = threading.RLock()
        self._closed = False
        self.metadata = self._start_metadata(metadata, resume)
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self._write_session()
            self._frames = _CsvFile(self.path / logs.FRAMES_FILE, logs.FRAMES_COLUMNS)
            self._force = _CsvFile(self.path / logs.FORCE_FILE, logs.FORCE_COLUMNS)
            self._printer = _CsvFile(self.path / logs.PRINTER_FILE, logs.PRINTER_COLUMNS)
            self._events = _CsvFile(self.path / logs.EVENTS_FILE, None)
        except OSError as e:
            raise logs.RecordingError(
                f"{self.path}: cannot create recording ({describe_os_error(e)})"
            ) from None
        existing = [
            int(m.group(1))
            for p in self.path.glob("video_*.avi")
            if (m := logs.VIDEO_PATTERN.fullmatch(p.name))
        ]
        self._chunk = max(existing) + 1 if existing else 0
        self._in_chunk = 0
        self._video: MjpgAviWriter | None = None
        self.frames_written = 0
        self.readings_written = 0

    def _start_metadata(self, metadata: dict[str, Any], resume: bool) -> dict[str, Any]:
        meta_path = self.path / logs.SESSION_FILE
        if resume:
            if not meta_path.exists():
                raise logs.RecordingError(f"{meta_path}: nothing to resume (no session.json)")
            previous = read_json(meta_path)
        else:
            if self.path.exists() and any(self.path.iterdir()):
                raise logs.RecordingError(
                    f"{self.path}: output folder exists and is not empty; choose a new folder "
                    "or resume the session"
                )
            previous = {}
        now = time.time()
        base = {
            "format": logs.RAW_FORMAT,
            "format_version": logs.RAW_FORMAT_VERSION,
            "software": {"beadsight": __version__},
            "created_unix": now,
            "camera": {"height": self.frame_hw[0], "width": self.frame_hw[1], "fps": self.fps},
            "video": {
                "fourcc": logs.VIDEO_FOURCC,
                "chunk_frames": self.chunk_frames,
                "jpeg_quality": self.jpeg_quality,
            },
            "sessions": [],
        }
        merged = {**base, **previous, **metadata}
        merged["status"] = "recording"
        merged.setdefault("sessions", []).append({"start_unix": now})
        return merged

    def _write_session(self) -> None:
        """Replace session.json atomically; RecordingError naming it if the disk refuses."""
        try:
            atomic_write_json(self.path / logs.SESSION_FILE, self.metadata)
        except WriteError as e:
            raise logs.RecordingError(str(e)) from None

    # --- streams -----------------------------------------------------------------------
    def write_frame(
        self, image: np.ndarray, *, t_unix: float, t_mono: float, camera_index: int
    ) -> None:
        """image: (H, W, 3) uint8 BGR of ``frame_hw``; times in s (float64)."""
        if image.shape != (*self.frame_hw, 3) or image.dtype != np.uint8:
            raise logs.RecordingError(
                f"{self.path}: frame is {image.shape} {image.dtype}; the recording expects "
                f"({self.frame_hw[0]}, {self.frame_hw[1]}, 3) uint8"
            )
        with self._lock:
            self._check_open()
            if self._video is None:
                self._open_chunk()
            assert self._video is not None
            try:
                self._video.write(image)
            except OSError as e:
                video, self._video = self._video, None
                video.close()  # releases the file, cut short; frames.csv keeps its frames
                path = video.path
                raise logs.RecordingError(
                    f"{path}: write failed ({describe_os_error(e)}); data flushed before this "
                    "point is kept"
                ) from None
            self._frames.write(
                f"{self._chunk},{self._in_chunk},{fmt_float(t_unix)},{fmt_float(t_mono)},"
                f"{int(camera_index)}"
            )
            self._in_chunk += 1
            self.frames_written += 1
            if self._in_chunk >= self.chunk_frames:
                self._close_chunk()

    def write_readings(self, readings: Sequence[Any]) -> None:
        """Scale readings (objects with t_unix, t_mono, grams, seq, device_ms)."""
        for r in readings:
            dev = getattr(r, "device_ms", None)
            self._force.write(
                f"{fmt_float(r.t_unix)},{fmt_float(r.t_mono)},{float(r.grams)!r},"
                f"{int(r.seq)},{'' if dev is None else int(dev)}"
            )
            self.readings_written += 1

    def write_command(self, record: Any, press: int = -1) -> None:
        """One executed printer command (t_unix, t_mono, gcode, x_mm, y_mm, z_mm);
        ``press`` >= 0 marks the finger being at that press's location afterwards."""
        gcode = str(record.gcode).replace(",", " ").replace("\n", " ").strip()
        self._printer.write(
            f"{fmt_float(record.t_unix)},{fmt_float(record.t_mono)},{gcode},"
            f"{fmt_float(record.x_mm)},{fmt_float(record.y_mm)},{fmt_float(record.z_mm)},"
            f"{int(press)}"
        )

    def log_event(self, event: str, **fields: Any) -> dict[str, Any]:
        """Append an event (press_start, press_end, press_abort, error, ...) and flush it."""
        t_unix, t_mono = time.time(), time.monotonic()
        record = {"event": event, "t_unix": t_unix, "t_mono": t_mono, **fields}
        self._events.write(json.dumps(record, default=str))
        try:
            self._events.flush(fsync=False)
        except OSError as e:
            raise logs.RecordingError(
                f"{self.path / logs.EVENTS_FILE}: write failed ({describe_os_error(e)})"
            ) from None
        return record

    def update_metadata(self, **fields: Any) -> None:
        with self._lock:
            self.metadata.update(fields)
            self._write_session()

    # --- chunks and flushing ----------------------------------------------------------------
    def _video_path(self, chunk: int) -> Path:
        return self.path / logs.VIDEO_NAME.format(chunk)

    def _open_chunk(self) -> None:
        path = self._video_path(self._chunk)
        try:
            self._video = MjpgAviWriter(path, self.frame_hw, self.fps, self.jpeg_quality)
        except OSError as e:
            raise logs.RecordingError(
                f"{path}: cannot create video chunk ({describe_os_error(e)})"
            ) from None
        self._in_chunk = 0

    def _close_chunk(self) -> None:
        video, self._video = self._video, None
        if video is None:
            return
        self._chunk += 1
        self._in_chunk = 0
        try:
            video.close()
        except OSError as e:
            raise logs.RecordingError(
                f"{video.path}: write failed ({describe_os_error(e)}); earlier chunks are kept"
            ) from None
        self.flush(fsync=True)
        fsync_dir(self.path)

    def flush(self, fsync: bool = False) -> None:
        """Flush all logs (and fsync them)."""
        for f in (self._frames, self._force, self._printer, self._events):
            try:
                f.flush(fsync)
            except OSError as e:
                raise logs.RecordingError(
                    f"{f.path}: write failed ({describe_os_error(e)}); data flushed before "
                    "this point is kept"
                ) from None

    def _check_open(self) -> None:
        if self._closed:
            raise logs.RecordingError(f"{self.path}: recording already closed")

    def close(self, status: str = "complete", **fields: Any) -> None:
        """Close the open chunk and all files; record ``status`` in session.json.

        Safe to call twice and after a write error (it closes what it can).
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            errors = []
            try:
                self._close_chunk()
            except (logs.RecordingError, OSError) as e:
                errors.append(str(e))
            for f in (self._frames, self._force, self._printer, self._events):
                try:
                    f.close()
                except OSError as e:
                    errors.append(f"{f.path}: {describe_os_error(e)}")
            now = time.time()
            self.metadata["sessions"][-1]["end_unix"] = now
            self.metadata["sessions"][-1]["status"] = status
            self.metadata.update(
                status=status, ended_unix=now, frames=self.frames_written, **fields
            )
            try:
                self._write_session()
            except logs.RecordingError as e:
                errors.append(str(e))
            if errors:
                raise logs.RecordingError(
                    f"{self.path}: closing the recording: " + "; ".join(errors)
                )

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        status = (
            "complete"
            if exc_type is None
            else ("interrupted" if issubclass(exc_type, KeyboardInterrupt) else "error")
        )
        try:
            self.close(status)
        except logs.RecordingError:
            if exc_type is None:
                raise
            logger.exception("closing %s after an error", self.path)
