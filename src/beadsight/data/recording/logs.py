"""The recorded streams of a raw session, as arrays, and the names of the files they live in.

Both readers (:mod:`.ours`, :mod:`.reference`) fill the same :class:`Recording`;
every row remembers the line (record) of its file it came from, so a problem found
later (a timestamp going backwards, an implausible force) can be reported as
``force_log.txt line 812``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.errors import BeadSightError

__all__ = [
    "DEFAULT_FPS",
    "EVENTS_FILE",
    "FORCE_COLUMNS",
    "FORCE_FILE",
    "FRAMES_COLUMNS",
    "FRAMES_FILE",
    "JPEG_QUALITY",
    "PRINTER_COLUMNS",
    "PRINTER_FILE",
    "RAW_FORMAT",
    "RAW_FORMAT_VERSION",
    "REF_FORCE_FILE",
    "REF_PARAMS_FILE",
    "REF_PRINTER_FILE",
    "REF_VIDEO_LOG",
    "REFERENCE_RAW_FORMAT",
    "SESSION_FILE",
    "VIDEO_FOURCC",
    "VIDEO_NAME",
    "ForceLog",
    "FrameLog",
    "MoveLog",
    "Recording",
    "RecordingError",
]

RAW_FORMAT = "beadsight-raw"
RAW_FORMAT_VERSION = 1
REFERENCE_RAW_FORMAT = "reference-raw"

SESSION_FILE = "session.json"
FRAMES_FILE = "frames.csv"
FORCE_FILE = "force.csv"
PRINTER_FILE = "printer.csv"
EVENTS_FILE = "events.jsonl"
VIDEO_NAME = "video_{:04d}.avi"
VIDEO_PATTERN = re.compile(r"video_(\d+)\.avi")
VIDEO_FOURCC = "MJPG"
JPEG_QUALITY = 90  # MJPG frames; raw 1280x1024 bead images take ~150 KB each

FRAMES_COLUMNS = ("chunk", "index", "t_unix", "t_mono", "camera_index")
FORCE_COLUMNS = ("t_unix", "t_mono", "grams", "seq", "device_ms")
PRINTER_COLUMNS = ("t_unix", "t_mono", "gcode", "x", "y", "z", "press")

REF_FORCE_FILE = "force_log.txt"
REF_PRINTER_FILE = "printer_log.txt"
REF_PARAMS_FILE = "experiment_parameters.json"
REF_VIDEO_LOG = re.compile(r"video_log_(\d+)\.txt$")
REF_VIDEO_LOG_NAME = "video_log_{}.txt"
REF_VIDEO_NAME = "video_{}.avi"

DEFAULT_FPS = 30.0


class RecordingError(BeadSightError):
    """A raw recording is missing, foreign, or could not be written; the message names it."""


def _no_lines() -> np.ndarray:
    return np.zeros(0, np.int64)


@dataclass
class FrameLog:
    """One row per logged frame, in recording order.

    chunk: (N,) int32 video chunk; index: (N,) int32 frame index inside that chunk;
    t_unix: (N,) float64 s; t_mono: (N,) float64 s (NaN where not recorded);
    camera_index: (N,) int64 capture counter of the camera (gaps = dropped frames);
    line: (N,) int64 line of the frame log each row came from (1-based).
    """

    chunk: np.ndarray
    index: np.ndarray
    t_unix: np.ndarray
    t_mono: np.ndarray
    camera_index: np.ndarray
    line: np.ndarray = field(default_factory=_no_lines)

    def __len__(self) -> int:
        return len(self.t_unix)


@dataclass
class ForceLog:
    """Scale readings. t_unix, t_mono: (M,) float64 s (t_mono NaN where absent);
    force_n: (M,) float64 N; grams: (M,) float64 g; seq: (M,) int64 (-1 where absent);
    line: (M,) int64 line of the force log (1-based)."""

    t_unix: np.ndarray
    t_mono: np.ndarray
    force_n: np.ndarray
    grams: np.ndarray
    seq: np.ndarray
    line: np.ndarray = field(default_factory=_no_lines)

    def __len__(self) -> int:
        return len(self.t_unix)


@dataclass
class MoveLog:
    """Executed printer commands.

    t_unix, t_mono: (K,) float64 s; xyz_mm: (K, 3) float64 absolute printer position
    after the command (NaN where unknown); offset_mm: (K, 2) float64 XY from the sensor
    centre (printer frame); is_data: (K,) bool, whether the finger is at a press
    location after this command (False for homing, parking, non-data moves);
    press: (K,) int64 press index (-1 for non-data); gcode: the command texts (a
    reference record may hold several G-code lines, joined by ``\\n``); line: (K,)
    int64 line (record) of the printer log (1-based).
    """

    t_unix: np.ndarray
    t_mono: np.ndarray
    xyz_mm: np.ndarray
    offset_mm: np.ndarray
    is_data: np.ndarray
    press: np.ndarray
    gcode: list[str]
    line: np.ndarray = field(default_factory=_no_lines)

    def __len__(self) -> int:
        return len(self.t_unix)


@dataclass
class Recording:
    """A raw session opened for reading (either format).

    ``videos[k]`` is the file of chunk ``k`` (None if missing); ``frames.chunk`` refers
    to these keys. ``frame_hw`` is the (rows, cols) of the video frames. ``files``
    names the file each stream was read from ("frames", "force", "moves"); the frame
    log name may hold ``{chunk}`` (the reference keeps one log per video).
    ``force_counter`` says whether the force log carried the reference sketch's
    counter and what was done about it (see :mod:`.counter`).
    """

    path: Path
    format: str
    metadata: dict[str, Any]
    frames: FrameLog
    force: ForceLog
    moves: MoveLog
    events: list[dict[str, Any]]
    videos: dict[int, Path]
    fps: float
    frame_hw: tuple[int, int] | None
    centre_xy_mm: tuple[float, float]
    warnings: list[str] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)
    force_counter: dict[str, Any] = field(default_factory=dict)

    @property
    def has_monotonic(self) -> bool:
        """Whether every stream carries the monotonic clock (preferred for alignment)."""
        return bool(
            len(self.frames)
            and np.isfinite(self.frames.t_mono).all()
            and (len(self.force) == 0 or np.isfinite(self.force.t_mono).all())
            and (len(self.moves) == 0 or np.isfinite(self.moves.t_mono).all())
        )

    def completed_presses(self) -> set[int]:
        """Press indices with a ``press_end`` or ``press_abort`` event (for ``--resume``)."""
        return {
            int(e["press"])
            for e in self.events
            if e.get("event") in ("press_end", "press_abort") and "press" in e
        }

    def where(self, stream: str, row: int) -> str:
        """``"<folder>/force_log.txt line 812"``: where row ``row`` of a stream was read.

        stream: "frames", "force" or "moves".
        """
        log = getattr(self, stream)
        name = self.files.get(stream, stream)
        if "{chunk}" in name:
            name = name.format(chunk=int(log.chunk[row]))
        line = int(log.line[row]) if len(log.line) > row else row + 1
        return f"{self.path / name} line {line}"
