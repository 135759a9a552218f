"""Raw recording sessions: this project's folder format (writer + reader) and the reference's.

This project's format (``docs/recording-format.md``) is a folder::

    session.json      metadata, written first, replaced atomically on every update
    video_0000.avi    MJPG video in chunks of ``chunk_frames`` frames (~1 s each)
    frames.csv        chunk,index,t_unix,t_mono,camera_index   (one row per frame)
    force.csv         t_unix,t_mono,grams,seq,device_ms        (one row per scale reading)
    printer.csv       t_unix,t_mono,gcode,x,y,z,press          (one row per executed command)
    events.jsonl      {"event": ..., "t_unix": ..., "t_mono": ..., ...} per line

Files are appended as data arrives, flushed and fsync'ed at every chunk boundary,
so a crash loses at most the last chunk (about one second).

The **reference raw format** (reference-facts section 5) is a folder with
``video_k.avi`` + ``video_log_k.txt`` (``unix_time,frame_number,video_path``),
``force_log.txt`` (``unix_time,value``, no header), ``printer_log.txt`` (records
separated by ``\\r``: ``unix_time,x,y,gcode``; x = y = -1 for non-data moves) and
``experiment_parameters.json``.

:func:`open_recording` reads either into one :class:`Recording`. A last line
without its line terminator (a crash mid-write), unparsable lines, and frames
listed but missing from a truncated video are tolerated and listed in
``Recording.warnings``.
"""

from __future__ import annotations

import errno
import io
import json
import logging
import math
import os
import re
import struct
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from beadsight import __version__
from beadsight.config import REFERENCE_CENTRE_XY_MM, REFERENCE_G_TO_N
from beadsight.errors import BeadSightError
from beadsight.geometry import force_to_newtons

logger = logging.getLogger(__name__)

RAW_FORMAT = "beadsight-raw"
RAW_FORMAT_VERSION = 1
REFERENCE_RAW_FORMAT = "reference-raw"

SESSION_FILE = "session.json"
FRAMES_FILE = "frames.csv"
FORCE_FILE = "force.csv"
PRINTER_FILE = "printer.csv"
EVENTS_FILE = "events.jsonl"
VIDEO_NAME = "video_{:04d}.avi"
VIDEO_FOURCC = "MJPG"
JPEG_QUALITY = 90  # MJPG frames; raw 1280x1024 bead images take ~150 KB each

FRAMES_COLUMNS = ("chunk", "index", "t_unix", "t_mono", "camera_index")
FORCE_COLUMNS = ("t_unix", "t_mono", "grams", "seq", "device_ms")
PRINTER_COLUMNS = ("t_unix", "t_mono", "gcode", "x", "y", "z", "press")

REF_FORCE_FILE = "force_log.txt"
REF_PRINTER_FILE = "printer_log.txt"
REF_PARAMS_FILE = "experiment_parameters.json"
REF_VIDEO_LOG = re.compile(r"video_log_(\d+)\.txt$")
GCODE_ROUNDING_MM = 0.01  # G-code coordinates are written with 2-3 decimals
SAME_XY_TOLERANCE_MM = 1e-3  # data moves closer than this belong to the same press
REF_NON_DATA_XY = -1.0  # the reference logs x = y = -1 for moves that are not at a press

DEFAULT_FPS = 30.0


class RecordingError(BeadSightError):
    """A raw recording is missing, foreign, or could not be written; the message names it."""


# --- the recorded streams ---------------------------------------------------------------
@dataclass
class FrameLog:
    """One row per logged frame, in recording order.

    chunk: (N,) int32 video chunk; index: (N,) int32 frame index inside that chunk;
    t_unix: (N,) float64 s; t_mono: (N,) float64 s (NaN where not recorded);
    camera_index: (N,) int64 capture counter of the camera (gaps = dropped frames).
    """

    chunk: np.ndarray
    index: np.ndarray
    t_unix: np.ndarray
    t_mono: np.ndarray
    camera_index: np.ndarray

    def __len__(self) -> int:
        return len(self.t_unix)


@dataclass
class ForceLog:
    """Scale readings. t_unix, t_mono: (M,) float64 s (t_mono NaN where absent);
    force_n: (M,) float64 N; grams: (M,) float64 g; seq: (M,) int64 (-1 where absent)."""

    t_unix: np.ndarray
    t_mono: np.ndarray
    force_n: np.ndarray
    grams: np.ndarray
    seq: np.ndarray

    def __len__(self) -> int:
        return len(self.t_unix)


@dataclass
class MoveLog:
    """Executed printer commands.

    t_unix, t_mono: (K,) float64 s; xyz_mm: (K, 3) float64 absolute printer position
    after the command (NaN where unknown); offset_mm: (K, 2) float64 XY from the sensor
    centre (printer frame); is_data: (K,) bool, whether the finger is at a press
    location after this command (False for homing, parking, non-data moves);
    press: (K,) int64 press index (-1 for non-data); gcode: the command texts.
    """

    t_unix: np.ndarray
    t_mono: np.ndarray
    xyz_mm: np.ndarray
    offset_mm: np.ndarray
    is_data: np.ndarray
    press: np.ndarray
    gcode: list[str]

    def __len__(self) -> int:
        return len(self.t_unix)


@dataclass
class Recording:
    """A raw session opened for reading (either format).

    ``videos[k]`` is the file of chunk ``k`` (None if missing); ``frames.chunk`` refers
    to these keys. ``frame_hw`` is the (rows, cols) of the video frames.
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


# --- small text-file helpers --------------------------------------------------------------
def _read_records(path: Path, sep: str, warnings: list[str]) -> list[str]:
    """Records of a text file split on ``sep``; a last record without its terminator is
    dropped as truncated (a crash mid-write) and reported."""
    data = path.read_bytes().decode("utf-8", errors="replace")
    if sep == "\r":
        data = data.replace("\r\n", "\r").replace("\n", "\r")
    records = data.split(sep)
    tail = records.pop()  # text after the last terminator: '' when complete
    if tail.strip():
        warnings.append(f"{path.name}: last record is truncated ({tail[:40]!r}); dropped")
    return [r for r in records if r.strip()]


def _parse_rows(
    path: Path,
    records: Sequence[str],
    ncols: int,
    warnings: list[str],
    header: tuple[str, ...] | None,
) -> list[list[str]]:
    """Split CSV records into ``ncols`` fields (the last field may contain commas)."""
    rows = []
    bad = 0
    for k, rec in enumerate(records):
        parts = rec.strip().split(",", ncols - 1)
        if k == 0 and header is not None and parts and parts[0] == header[0]:
            continue
        if len(parts) != ncols:
            bad += 1
            continue
        rows.append(parts)
    if bad:
        warnings.append(f"{path.name}: skipped {bad} malformed line(s) (expected {ncols} fields)")
    return rows


def _floats(rows: list[list[str]], col: int, path: Path, warnings: list[str]) -> np.ndarray:
    out = np.empty(len(rows), dtype=np.float64)
    bad = 0
    for i, r in enumerate(rows):
        text = r[col].strip()
        try:
            out[i] = float(text) if text else math.nan
        except ValueError:
            out[i] = math.nan
            bad += 1
    if bad:
        warnings.append(f"{path.name}: {bad} unparsable number(s) in column {col + 1}")
    return out


def _json_lines(path: Path, warnings: list[str]) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    out = []
    for k, rec in enumerate(_read_records(path, "\n", warnings)):
        try:
            obj = json.loads(rec)
        except json.JSONDecodeError:
            warnings.append(f"{path.name}: line {k + 1} is not valid JSON; skipped")
            continue
        if isinstance(obj, dict):
            out.append(obj)
    return out


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise RecordingError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise RecordingError(f"{path}: expected a JSON object")
    return data


def _probe_video(path: Path) -> tuple[tuple[int, int] | None, float | None]:
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            return None, None
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = cap.get(cv2.CAP_PROP_FPS)
        return ((h, w) if w > 0 and h > 0 else None), (fps if fps and fps > 0 else None)
    finally:
        cap.release()


def read_session(path: str | Path) -> dict[str, Any]:
    """The ``session.json`` of a recording folder (RecordingError if missing or malformed)."""
    meta = Path(path) / SESSION_FILE
    if not meta.exists():
        raise RecordingError(f"{meta}: not found (not a beadsight raw recording?)")
    return _read_json(meta)


def read_events(path: str | Path) -> list[dict[str, Any]]:
    """The events of a recording folder, oldest first (a torn last line is skipped)."""
    return _json_lines(Path(path) / EVENTS_FILE, [])


# --- opening ------------------------------------------------------------------------------
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


def open_recording(path: str | Path) -> Recording:
    """Read a raw session folder of either format (videos stay on disk)."""
    path = Path(path)
    fmt = detect_format(path)
    rec = _open_beadsight(path) if fmt == RAW_FORMAT else _open_reference(path)
    for w in rec.warnings:
        logger.warning("%s: %s", path, w)
    return rec


def _open_beadsight(path: Path) -> Recording:
    warnings: list[str] = []
    meta_path = path / SESSION_FILE
    metadata = _read_json(meta_path) if meta_path.exists() else {}
    if not metadata:
        warnings.append(f"{SESSION_FILE} missing; using defaults")
    fmt = metadata.get("format", RAW_FORMAT)
    if fmt != RAW_FORMAT:
        raise RecordingError(f"{meta_path}: field 'format' is {fmt!r}, expected {RAW_FORMAT!r}")
    if int(metadata.get("format_version", 1)) > RAW_FORMAT_VERSION:
        raise RecordingError(
            f"{meta_path}: format_version {metadata['format_version']} is newer than this "
            f"beadsight reads ({RAW_FORMAT_VERSION}); upgrade beadsight"
        )
    frames_path = path / FRAMES_FILE
    if not frames_path.exists():
        raise RecordingError(f"{frames_path}: frame log not found")
    rows = _parse_rows(
        frames_path,
        _read_records(frames_path, "\n", warnings),
        len(FRAMES_COLUMNS),
        warnings,
        FRAMES_COLUMNS,
    )
    f = [_floats(rows, k, frames_path, warnings) for k in range(len(FRAMES_COLUMNS))]
    ok = np.isfinite(f[0]) & np.isfinite(f[1]) & np.isfinite(f[2])
    frames = FrameLog(
        chunk=f[0][ok].astype(np.int32),
        index=f[1][ok].astype(np.int32),
        t_unix=f[2][ok],
        t_mono=f[3][ok],
        camera_index=np.where(np.isfinite(f[4][ok]), f[4][ok], -1).astype(np.int64),
    )
    centre = tuple(float(v) for v in metadata.get("centre_xy_mm", REFERENCE_CENTRE_XY_MM))
    force = _read_beadsight_force(path / FORCE_FILE, warnings)
    moves = _read_beadsight_printer(path / PRINTER_FILE, centre, warnings)
    events = _json_lines(path / EVENTS_FILE, warnings)
    videos = {
        int(m.group(1)): p
        for p in sorted(path.glob("video_*.avi"))
        if (m := re.fullmatch(r"video_(\d+)\.avi", p.name))
    }
    camera = metadata.get("camera", {})
    fps = float(camera.get("fps") or DEFAULT_FPS)  # host frame rate (virtual rigs: scaled)
    frame_hw = None
    if camera.get("height") and camera.get("width"):
        frame_hw = (int(camera["height"]), int(camera["width"]))
    elif videos:
        frame_hw = _probe_video(next(iter(videos.values())))[0]
    status = metadata.get("status")
    if status not in (None, "complete"):
        warnings.append(f"session status is {status!r} (not 'complete')")
    return Recording(
        path,
        RAW_FORMAT,
        metadata,
        frames,
        force,
        moves,
        events,
        videos,
        fps,
        frame_hw,
        centre,
        warnings,
    )


def _read_beadsight_force(path: Path, warnings: list[str]) -> ForceLog:
    if not path.exists():
        warnings.append(f"{path.name} missing: no force readings")
        rows: list[list[str]] = []
    else:
        rows = _parse_rows(
            path, _read_records(path, "\n", warnings), len(FORCE_COLUMNS), warnings, FORCE_COLUMNS
        )
    t_unix, t_mono, grams, seq = (_floats(rows, k, path, warnings) for k in range(4))
    ok = np.isfinite(t_unix) & np.isfinite(grams)
    return ForceLog(
        t_unix=t_unix[ok],
        t_mono=t_mono[ok],
        force_n=grams[ok] * REFERENCE_G_TO_N,
        grams=grams[ok],
        seq=np.where(np.isfinite(seq[ok]), seq[ok], -1).astype(np.int64),
    )


def _read_beadsight_printer(
    path: Path, centre: tuple[float, float], warnings: list[str]
) -> MoveLog:
    if not path.exists():
        warnings.append(f"{path.name} missing: no printer commands")
        rows: list[list[str]] = []
    else:
        # gcode (3rd column) has no commas: split on all of them
        rows = []
        bad = 0
        for k, rec in enumerate(_read_records(path, "\n", warnings)):
            parts = rec.strip().split(",")
            if k == 0 and parts[0] == PRINTER_COLUMNS[0]:
                continue
            if len(parts) != len(PRINTER_COLUMNS):
                bad += 1
                continue
            rows.append(parts)
        if bad:
            warnings.append(f"{path.name}: skipped {bad} malformed line(s)")
    t_unix, t_mono = (_floats(rows, k, path, warnings) for k in range(2))
    xyz = np.stack([_floats(rows, k, path, warnings) for k in (3, 4, 5)], axis=1).reshape(-1, 3)
    press = _floats(rows, 6, path, warnings)
    ok = np.isfinite(t_unix)
    press = np.where(np.isfinite(press), press, -1).astype(np.int64)[ok]
    xyz = xyz[ok]
    is_data = (press >= 0) & np.isfinite(xyz[:, :2]).all(axis=1)
    return MoveLog(
        t_unix=t_unix[ok],
        t_mono=t_mono[ok],
        xyz_mm=xyz,
        offset_mm=xyz[:, :2] - np.asarray(centre),
        is_data=is_data,
        press=press,
        gcode=[r[2] for r, keep in zip(rows, ok, strict=True) if keep],
    )


# --- the reference raw format ------------------------------------------------------------
_GCODE_AXIS = re.compile(r"\b([XYZ])\s*(-?\d+(?:\.\d*)?|-?\.\d+)", re.IGNORECASE)


def _gcode_xy(gcode: str) -> tuple[float, float] | None:
    axes = {m.group(1).upper(): float(m.group(2)) for m in _GCODE_AXIS.finditer(gcode)}
    if "X" in axes and "Y" in axes:
        return axes["X"], axes["Y"]
    return None


def _open_reference(path: Path) -> Recording:
    warnings: list[str] = []
    params_path = path / REF_PARAMS_FILE
    params = _read_json(params_path) if params_path.exists() else {}
    if not params:
        warnings.append(f"{REF_PARAMS_FILE} missing; assuming the reference rig's defaults")
    centre = tuple(float(v) for v in params.get("center", REFERENCE_CENTRE_XY_MM))[:2]
    fps = float(params.get("fps", DEFAULT_FPS))
    frames, videos = _read_reference_frames(path, warnings)
    force = _read_reference_force(path / REF_FORCE_FILE, params, warnings)
    moves = _read_reference_printer(path / REF_PRINTER_FILE, centre, params, warnings)
    frame_hw = _probe_video(next(iter(videos.values())))[0] if videos else None
    metadata = {"format": REFERENCE_RAW_FORMAT, "experiment_parameters": params}
    return Recording(
        path,
        REFERENCE_RAW_FORMAT,
        metadata,
        frames,
        force,
        moves,
        [],
        videos,
        fps,
        frame_hw,
        centre,
        warnings,
    )


def _read_reference_frames(path: Path, warnings: list[str]) -> tuple[FrameLog, dict[int, Path]]:
    logs = sorted(
        ((int(m.group(1)), p) for p in path.iterdir() if (m := REF_VIDEO_LOG.search(p.name))),
        key=lambda kp: kp[0],
    )
    if not logs:
        raise RecordingError(f"{path}: no video_log_k.txt frame logs found")
    chunk, index, t_unix, cam = [], [], [], []
    videos: dict[int, Path] = {}
    for k, log in logs:
        video = path / f"video_{k}.avi"
        if video.exists():
            videos[k] = video
        else:
            warnings.append(f"{video.name} missing: {log.name} lists frames without video")
        rows = _parse_rows(log, _read_records(log, "\n", warnings), 3, warnings, None)
        t = _floats(rows, 0, log, warnings)
        n = _floats(rows, 1, log, warnings)
        ok = np.isfinite(t)
        chunk.append(np.full(int(ok.sum()), k, np.int32))
        index.append(np.arange(int(ok.sum()), dtype=np.int32))  # line order = frame order
        t_unix.append(t[ok])
        cam.append(np.where(np.isfinite(n[ok]), n[ok], -1).astype(np.int64))
    t_all = np.concatenate(t_unix)
    frames = FrameLog(
        chunk=np.concatenate(chunk),
        index=np.concatenate(index),
        t_unix=t_all,
        t_mono=np.full(len(t_all), np.nan),
        camera_index=np.concatenate(cam),
    )
    return frames, videos


def _read_reference_force(path: Path, params: dict, warnings: list[str]) -> ForceLog:
    if not path.exists():
        warnings.append(f"{path.name} missing: no force readings")
        rows: list[list[str]] = []
    else:
        rows = _parse_rows(path, _read_records(path, "\n", warnings), 2, warnings, None)
    t = _floats(rows, 0, path, warnings)
    value = _floats(rows, 1, path, warnings)
    ok = np.isfinite(t) & np.isfinite(value)
    unit = str(params.get("force_unit", "g"))
    try:
        force_n = force_to_newtons(value[ok], unit)
    except ValueError as e:
        raise RecordingError(f"{path.parent / REF_PARAMS_FILE}: field 'force_unit': {e}") from None
    grams = force_n / REFERENCE_G_TO_N
    return ForceLog(
        t[ok], np.full(int(ok.sum()), np.nan), force_n, grams, np.full(int(ok.sum()), -1, np.int64)
    )


def _read_reference_printer(
    path: Path, centre: tuple[float, float], params: dict, warnings: list[str]
) -> MoveLog:
    """Reference printer log: x, y are the press location; x = y = -1 marks non-data moves.

    Whether x, y are absolute printer coordinates or offsets from the sensor centre is
    decided from the data: if the G-code's own X/Y equal the logged x, y, they are
    absolute; otherwise if they lie within the press range around 0 they are offsets.
    """
    if not path.exists():
        warnings.append(f"{path.name} missing: no printer commands")
        rows: list[list[str]] = []
    else:
        rows = _parse_rows(path, _read_records(path, "\r", warnings), 4, warnings, None)
    t = _floats(rows, 0, path, warnings)
    x = _floats(rows, 1, path, warnings)
    y = _floats(rows, 2, path, warnings)
    gcode = [r[3].strip() for r in rows]
    ok = np.isfinite(t) & np.isfinite(x) & np.isfinite(y)
    t, x, y = t[ok], x[ok], y[ok]
    gcode = [g for g, keep in zip(gcode, ok, strict=True) if keep]
    is_data = ~((x == REF_NON_DATA_XY) & (y == REF_NON_DATA_XY))
    absolute = _reference_xy_is_absolute(x[is_data], y[is_data], gcode, is_data, centre, params)
    xy = np.stack([x, y], axis=1)
    offset = xy - np.asarray(centre) if absolute else xy.copy()
    offset[~is_data] = np.nan
    xyz = np.full((len(t), 3), np.nan)
    if absolute:
        xyz[:, :2] = np.where(is_data[:, None], xy, np.nan)
    else:
        xyz[:, :2] = np.where(is_data[:, None], xy + np.asarray(centre), np.nan)
    press = _reference_press_index(xy, is_data)
    return MoveLog(t, np.full(len(t), np.nan), xyz, offset, is_data, press, gcode)


def _reference_press_index(xy: np.ndarray, is_data: np.ndarray) -> np.ndarray:
    """A press starts at a data move that follows a non-data move or changes the XY."""
    press = np.full(len(xy), -1, np.int64)
    current = -1
    previous: np.ndarray | None = None
    for k in range(len(xy)):
        if not is_data[k]:
            previous = None
            continue
        if previous is None or np.abs(xy[k] - previous).max() > SAME_XY_TOLERANCE_MM:
            current += 1
        previous = xy[k]
        press[k] = current
    return press


def _reference_xy_is_absolute(x, y, gcode, is_data, centre, params) -> bool:
    data_gcode = [g for g, d in zip(gcode, is_data, strict=True) if d]
    for xi, yi, g in zip(x, y, data_gcode, strict=True):
        xy = _gcode_xy(g)
        if xy is not None:
            return bool(
                abs(xy[0] - xi) <= GCODE_ROUNDING_MM and abs(xy[1] - yi) <= GCODE_ROUNDING_MM
            )
    if len(x) == 0:
        return False
    radius = float(params.get("radius", 13.75))
    near_zero = np.all(np.abs(x) <= radius * 1.5) and np.all(np.abs(y) <= radius * 1.5)
    return not near_zero


# --- reading video --------------------------------------------------------------------------
def iter_video(path: str | Path, *, packets: bool = False) -> Iterator[np.ndarray]:
    """Frames of one video file in order.

    ``packets=False``: (H, W, 3) uint8 BGR images. ``packets=True``: the encoded JPEG of
    each frame as a 1-D uint8 array (MJPG only; decode with ``cv2.imdecode``, possibly
    at reduced size) -- raises RecordingError if the video is not MJPG. Stops at the
    end of the file or at the first undecodable frame (a truncated chunk).
    """
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise RecordingError(f"{path}: cannot open video")
    try:
        if packets:
            cap.set(cv2.CAP_PROP_FORMAT, -1)
        while True:
            ok, item = cap.read()
            if not ok or item is None:
                return
            if packets:
                data = item.reshape(-1)
                if data[:2].tobytes() != b"\xff\xd8":
                    raise RecordingError(f"{path}: not an MJPG video (frames are not JPEG)")
                yield data.copy()
            else:
                yield item
    finally:
        cap.release()


def is_mjpg(path: str | Path) -> bool:
    """Whether a video's frames are JPEG images (readable as packets)."""
    try:
        next(iter_video(path, packets=True))
    except (RecordingError, StopIteration):
        return False
    return True


# --- writing ---------------------------------------------------------------------------------
def _fmt_float(v: float | None) -> str:
    """Full float64 precision (shortest round-trip repr); empty for None/NaN."""
    if v is None:
        return ""
    v = float(v)
    return "" if math.isnan(v) else repr(v)


def atomic_write_json(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to a temporary file, fsync it, rename it over ``path``, fsync the folder."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=2, default=str)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def _describe_os_error(e: OSError) -> str:
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        return "disk full"
    if e.errno == errno.EFBIG:
        return "file size limit reached"
    return e.strerror or str(e)


class MjpgAviWriter:
    """A minimal MJPG AVI writer: every frame is a JPEG in a ``00dc`` chunk.

    Written in Python (not ``cv2.VideoWriter``) so that a write error -- disk full, file
    size limit -- raises OSError at once instead of being logged and ignored, and so the
    JPEG quality is explicit. :meth:`close` appends the ``idx1`` index and fills in the
    header sizes; a file cut short by a crash still reads (demuxers scan the ``movi``
    list) up to its last whole frame.
    """

    _AVIF_HASINDEX = 0x10
    _AVIIF_KEYFRAME = 0x10
    _PLACEHOLDER = 0  # header sizes before close(); readers fall back to scanning

    def __init__(
        self, path: Path, frame_hw: tuple[int, int], fps: float, quality: int = JPEG_QUALITY
    ):
        self.path = path
        self.height, self.width = frame_hw
        self.fps = float(fps)
        self.quality = int(quality)
        self.frames = 0
        self._index: list[tuple[int, int]] = []  # (offset from 'movi', size)
        self._max_size = 0
        self._f = open(path, "wb")  # noqa: SIM115 - closed in close()
        try:
            self._write_headers()
        except BaseException:
            self._f.close()
            raise

    def _avih(self) -> bytes:
        return struct.pack(
            "<10I16x",
            round(1e6 / self.fps),
            0,
            0,
            self._AVIF_HASINDEX,
            self.frames,
            0,
            1,
            self._max_size,
            self.width,
            self.height,
        )

    def _strh(self) -> bytes:
        rate = round(self.fps * 1000)
        return struct.pack(
            "<4s4sIHHIIIIIIIIhhhh",
            b"vids",
            b"MJPG",
            0,
            0,
            0,
            0,
            1000,
            rate,
            0,
            self.frames,
            self._max_size,
            0xFFFFFFFF,
            0,
            0,
            0,
            self.width,
            self.height,
        )

    def _strf(self) -> bytes:
        return struct.pack(
            "<IiiHH4sIiiII",
            40,
            self.width,
            self.height,
            1,
            24,
            b"MJPG",
            self.width * self.height * 3,
            0,
            0,
            0,
            0,
        )

    def _write_headers(self) -> None:
        strl = b"strl" + _chunk(b"strh", self._strh()) + _chunk(b"strf", self._strf())
        hdrl = b"hdrl" + _chunk(b"avih", self._avih()) + _chunk(b"LIST", strl)
        self._f.write(b"RIFF" + struct.pack("<I", self._PLACEHOLDER) + b"AVI ")
        self._f.write(_chunk(b"LIST", hdrl))
        self._avih_at = 12 + 8 + 4 + 8  # RIFF hdr, LIST hdr, 'hdrl', 'avih' hdr
        self._strh_at = self._avih_at + 56 + 8 + 4 + 8  # avih, LIST hdr, 'strl', 'strh' hdr
        self._movi_at = self._f.tell()  # the movi LIST header
        self._f.write(b"LIST" + struct.pack("<I", self._PLACEHOLDER) + b"movi")

    def write(self, image: np.ndarray) -> None:
        """image: (H, W, 3) uint8 BGR; raises OSError when the disk refuses it."""
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise RecordingError(f"{self.path}: JPEG encoding failed")
        data = jpeg.tobytes()
        offset = self._f.tell() - (self._movi_at + 8)  # relative to the 'movi' fourcc
        self._f.write(_chunk(b"00dc", data))
        self._index.append((offset, len(data)))
        self._max_size = max(self._max_size, len(data))
        self.frames += 1

    def close(self) -> None:
        """Write the index, fill in the sizes, flush and fsync. Safe to call twice."""
        if self._f.closed:
            return
        try:
            end_movi = self._f.tell()
            idx = b"".join(
                struct.pack("<4sIII", b"00dc", self._AVIIF_KEYFRAME, off, size)
                for off, size in self._index
            )
            self._f.write(_chunk(b"idx1", idx))
            end = self._f.tell()
            self._f.seek(4)
            self._f.write(struct.pack("<I", end - 8))
            self._f.seek(self._movi_at + 4)
            self._f.write(struct.pack("<I", end_movi - self._movi_at - 8))
            self._f.seek(self._avih_at)
            self._f.write(self._avih())
            self._f.seek(self._strh_at)
            self._f.write(self._strh())
            self._f.flush()
            os.fsync(self._f.fileno())
        finally:
            self._f.close()


def _chunk(fourcc: bytes, data: bytes) -> bytes:
    """A RIFF chunk: fourcc, little-endian size, data, padded to an even length."""
    pad = b"\0" if len(data) % 2 else b""
    return fourcc + struct.pack("<I", len(data)) + data + pad


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
        jpeg_quality: int = JPEG_QUALITY,
    ):
        self.path = Path(path)
        self.jpeg_quality = int(jpeg_quality)
        self.frame_hw = (int(frame_hw[0]), int(frame_hw[1]))
        self.fps = float(fps)
        self.chunk_frames = int(chunk_frames or max(1, round(self.fps)))
        self._lock = threading.RLock()
        self._closed = False
        meta_path = self.path / SESSION_FILE
        if resume:
            if not meta_path.exists():
                raise RecordingError(f"{meta_path}: nothing to resume (no session.json)")
            self.metadata = _read_json(meta_path)
        else:
            if self.path.exists() and any(self.path.iterdir()):
                raise RecordingError(
                    f"{self.path}: output folder exists and is not empty; choose a new folder "
                    "or resume the session"
                )
            self.metadata = {}
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            now = time.time()
            base = {
                "format": RAW_FORMAT,
                "format_version": RAW_FORMAT_VERSION,
                "software": {"beadsight": __version__},
                "created_unix": now,
                "camera": {"height": self.frame_hw[0], "width": self.frame_hw[1], "fps": self.fps},
                "video": {
                    "fourcc": VIDEO_FOURCC,
                    "chunk_frames": self.chunk_frames,
                    "jpeg_quality": self.jpeg_quality,
                },
                "sessions": [],
            }
            self.metadata = (
                {**base, **self.metadata, **metadata} if resume else {**base, **metadata}
            )
            self.metadata["status"] = "recording"
            self.metadata.setdefault("sessions", []).append({"start_unix": now})
            atomic_write_json(meta_path, self.metadata)
            self._frames = _CsvFile(self.path / FRAMES_FILE, FRAMES_COLUMNS)
            self._force = _CsvFile(self.path / FORCE_FILE, FORCE_COLUMNS)
            self._printer = _CsvFile(self.path / PRINTER_FILE, PRINTER_COLUMNS)
            self._events = _CsvFile(self.path / EVENTS_FILE, None)
        except OSError as e:
            raise RecordingError(
                f"{self.path}: cannot create recording ({_describe_os_error(e)})"
            ) from None
        existing = [
            int(m.group(1))
            for p in self.path.glob("video_*.avi")
            if (m := re.fullmatch(r"video_(\d+)\.avi", p.name))
        ]
        self._chunk = max(existing) + 1 if existing else 0
        self._in_chunk = 0
        self._video: MjpgAviWriter | None = None
        self.frames_written = 0
        self.readings_written = 0

    # --- streams -----------------------------------------------------------------------
    def write_frame(
        self, image: np.ndarray, *, t_unix: float, t_mono: float, camera_index: int
    ) -> None:
        """image: (H, W, 3) uint8 BGR of ``frame_hw``; times in s (float64)."""
        if image.shape != (*self.frame_hw, 3) or image.dtype != np.uint8:
            raise RecordingError(
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
                path = self._video.path
                self._video = None  # the chunk is cut short; frames.csv keeps its frames
                raise RecordingError(
                    f"{path}: write failed ({_describe_os_error(e)}); data flushed before this "
                    "point is kept"
                ) from None
            self._frames.write(
                f"{self._chunk},{self._in_chunk},{_fmt_float(t_unix)},{_fmt_float(t_mono)},"
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
                f"{_fmt_float(r.t_unix)},{_fmt_float(r.t_mono)},{float(r.grams)!r},"
                f"{int(r.seq)},{'' if dev is None else int(dev)}"
            )
            self.readings_written += 1

    def write_command(self, record: Any, press: int = -1) -> None:
        """One executed printer command (t_unix, t_mono, gcode, x_mm, y_mm, z_mm);
        ``press`` >= 0 marks the finger being at that press's location afterwards."""
        gcode = str(record.gcode).replace(",", " ").replace("\n", " ").strip()
        self._printer.write(
            f"{_fmt_float(record.t_unix)},{_fmt_float(record.t_mono)},{gcode},"
            f"{_fmt_float(record.x_mm)},{_fmt_float(record.y_mm)},{_fmt_float(record.z_mm)},"
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
            raise RecordingError(
                f"{self.path / EVENTS_FILE}: write failed ({_describe_os_error(e)})"
            ) from None
        return record

    def update_metadata(self, **fields: Any) -> None:
        with self._lock:
            self.metadata.update(fields)
            try:
                atomic_write_json(self.path / SESSION_FILE, self.metadata)
            except OSError as e:
                raise RecordingError(
                    f"{self.path / SESSION_FILE}: write failed ({_describe_os_error(e)})"
                ) from None

    # --- chunks and flushing ----------------------------------------------------------------
    def _video_path(self, chunk: int) -> Path:
        return self.path / VIDEO_NAME.format(chunk)

    def _open_chunk(self) -> None:
        path = self._video_path(self._chunk)
        try:
            self._video = MjpgAviWriter(path, self.frame_hw, self.fps, self.jpeg_quality)
        except OSError as e:
            raise RecordingError(
                f"{path}: cannot create video chunk ({_describe_os_error(e)})"
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
            raise RecordingError(
                f"{video.path}: write failed ({_describe_os_error(e)}); earlier chunks are kept"
            ) from None
        self.flush(fsync=True)
        _fsync_dir(self.path)

    def flush(self, fsync: bool = False) -> None:
        """Flush all logs (and fsync them)."""
        for f in (self._frames, self._force, self._printer, self._events):
            try:
                f.flush(fsync)
            except OSError as e:
                raise RecordingError(
                    f"{f.path}: write failed ({_describe_os_error(e)}); data flushed before "
                    "this point is kept"
                ) from None

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"{self.path}: recording already closed")

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
            except (RecordingError, OSError) as e:
                errors.append(str(e))
            for f in (self._frames, self._force, self._printer, self._events):
                try:
                    f.close()
                except OSError as e:
                    errors.append(f"{f.path}: {_describe_os_error(e)}")
            now = time.time()
            self.metadata["sessions"][-1]["end_unix"] = now
            self.metadata["sessions"][-1]["status"] = status
            self.metadata.update(
                status=status, ended_unix=now, frames=self.frames_written, **fields
            )
            try:
                atomic_write_json(self.path / SESSION_FILE, self.metadata)
            except OSError as e:
                errors.append(f"{self.path / SESSION_FILE}: {_describe_os_error(e)}")
            if errors:
                raise RecordingError(f"{self.path}: closing the recording: " + "; ".join(errors))

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        status = (
            "complete"
            if exc_type is None
            else ("interrupted" if exc_type is KeyboardInterrupt else "error")
        )
        try:
            self.close(status)
        except RecordingError:
            if exc_type is None:
                raise
            logger.exception("closing %s after an error", self.path)
