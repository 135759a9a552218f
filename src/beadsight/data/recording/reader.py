"""Opening a raw session folder of either format as one :class:`Recording`."""

from __future__ import annotations

import logging
from pathlib import Path

from beadsight.data.recording.counter import apply_force_counter
from beadsight.data.recording.logs import (
    FRAMES_FILE,
    RAW_FORMAT,
    REF_FORCE_FILE,
    REF_VIDEO_LOG,
    REFERENCE_RAW_FORMAT,
    SESSION_FILE,
    Recording,
    RecordingError,
)
from beadsight.data.recording.ours import open_ours
from beadsight.data.recording.reference import open_reference

logger = logging.getLogger(__name__)


def detect_format(path: str | Path) -> str:
    """``"beadsight-raw"`` or ``"reference-raw"``; RecordingError if neither."""
    path = Path(path)
    if not path.is_dir():
        raise RecordingError(f"{path}: raw recording folder not found")
    if (path / SESSION_FILE).exists() or (path / FRAMES_FILE).exists():
        return RAW_FORMAT
    if (
        any(REF_VIDEO_LOG.search(p.name) for p in path.iterdir())
        or (path / REF_FORCE_FILE).exists()
    ):
        return REFERENCE_RAW_FORMAT
    raise RecordingError(
        f"{path}: not a raw recording: expected {SESSION_FILE} + {FRAMES_FILE} (beadsight) or "
        f"video_log_0.txt + {REF_FORCE_FILE} (reference)"
    )


def open_recording(path: str | Path, *, force_counter: str = "auto") -> Recording:
    """Read a raw session folder of either format (videos stay on disk).

    force_counter: "auto", "on" or "off": whether to decode the reference scale
    sketch's ``+10000*i`` counter from the force readings (:mod:`.counter`); what was
    found is in ``Recording.force_counter``.
    """
    path = Path(path)
    fmt = detect_format(path)
    rec = open_ours(path) if fmt == RAW_FORMAT else open_reference(path)
    name = rec.files.get("force", "force log")
    rec.force, rec.force_counter = apply_force_counter(rec.force, force_counter, name)
    if rec.force_counter["detected"] and not rec.force_counter["decoded"]:
        rec.warnings.append(rec.force_counter["message"])
    for w in rec.warnings:
        logger.warning("%s: %s", path, w)
    return rec
