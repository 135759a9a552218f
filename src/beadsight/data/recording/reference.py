"""Reading the reference rig's raw recording folder (reference-facts section 5).

* ``video_k.avi`` + ``video_log_k.txt``: one ``unix_time,frame_number,video_path`` line
  per frame;
* ``force_log.txt``: ``unix_time,value`` per scale line, no header (the value may carry
  the reference sketch's ``+10000*i`` counter: see :mod:`.counter`);
* ``printer_log.txt``: records that END with ``\\r``, each ``unix_time,x,y,gcode`` where
  the command block ``gcode`` holds several G-code lines separated by ``\\n``;
  ``x = y = -1`` marks moves that are not at a press;
* ``experiment_parameters.json``: ``fps``, ``center``, ``radius``, ``force_unit``, ...
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from beadsight.config import REFERENCE_CENTRE_XY_MM, REFERENCE_G_TO_N
from beadsight.data.recording import logs
from beadsight.data.recording.text import (
    finite_rows,
    floats,
    parse_rows,
    read_json,
    read_records,
    read_table,
)
from beadsight.data.recording.video import probe_video
from beadsight.geometry import force_to_newtons

GCODE_ROUNDING_MM = 0.01  # G-code coordinates are written with 2-3 decimals
SAME_XY_TOLERANCE_MM = 1e-3  # data moves closer than this belong to the same press
REF_NON_DATA_XY = -1.0  # the reference logs x = y = -1 for moves that are not at a press
OFFSET_RANGE_FACTOR = 1.5  # logged x, y within this times the press radius: offsets
_GCODE_AXIS = re.compile(r"\b([XYZ])\s*(-?\d+(?:\.\d*)?|-?\.\d+)", re.IGNORECASE)


def gcode_xy(gcode: str) -> tuple[float, float] | None:
    """The X and Y a command block moves to (the first line naming both), or None."""
    for line in gcode.splitlines():
        axes = {m.group(1).upper(): float(m.group(2)) for m in _GCODE_AXIS.finditer(line)}
        if "X" in axes and "Y" in axes:
            return axes["X"], axes["Y"]
    return None


def open_reference(path: Path) -> logs.Recording:
    """Read a reference raw recording folder (videos stay on disk)."""
    warnings: list[str] = []
    params_path = path / logs.REF_PARAMS_FILE
    params = read_json(params_path) if params_path.exists() else {}
    if not params:
        warnings.append(f"{logs.REF_PARAMS_FILE} missing; assuming the reference rig's defaults")
    centre = tuple(float(v) for v in params.get("center", REFERENCE_CENTRE_XY_MM))[:2]
    fps = float(params.get("fps", logs.DEFAULT_FPS))
    frames, videos = _read_frames(path, warnings)
    force = _read_force(path / logs.REF_FORCE_FILE, params, warnings)
    moves = _read_printer(path / logs.REF_PRINTER_FILE, centre, params, warnings)
    frame_hw = probe_video(next(iter(videos.values())))[0] if videos else None
    metadata = {"format": logs.REFERENCE_RAW_FORMAT, "experiment_parameters": params}
    files = {
        "frames": logs.REF_VIDEO_LOG_NAME.format("{chunk}"),
        "force": logs.REF_FORCE_FILE,
        "moves": logs.REF_PRINTER_FILE,
    }
    return logs.Recording(
        path,
        logs.REFERENCE_RAW_FORMAT,
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
        files,
    )


def _read_frames(path: Path, warnings: list[str]) -> tuple[logs.FrameLog, dict[int, Path]]:
    frame_logs = sorted(
        ((int(m.group(1)), p) for p in path.iterdir() if (m := logs.REF_VIDEO_LOG.search(p.name))),
        key=lambda kp: kp[0],
    )
    if not frame_logs:
        raise logs.RecordingError(f"{path}: no video_log_k.txt frame logs found")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("chunk", "index", "t", "cam", "line")}
    videos: dict[int, Path] = {}
    for k, log in frame_logs:
        video = path / logs.REF_VIDEO_NAME.format(k)
        if video.exists():
            videos[k] = video
        else:
            warnings.append(f"{video.name} missing: {log.name} lists frames without video")
        table = parse_rows(log, read_records(log, "\n", warnings), 3, warnings)
        t = floats(table, 0, warnings, "unix_time")
        n = floats(table, 1, warnings, "frame_number")
        ok = finite_rows(table, {"unix_time": t}, warnings)
        count = int(ok.sum())
        parts["chunk"].append(np.full(count, k, np.int32))
        parts["index"].append(np.arange(count, dtype=np.int32))  # line order = frame order
        parts["t"].append(t[ok])
        parts["cam"].append(np.where(np.isfinite(n[ok]), n[ok], -1).astype(np.int64))
        parts["line"].append(table.lines[ok])
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    frames = logs.FrameLog(
        chunk=cat["chunk"],
        index=cat["index"],
        t_unix=cat["t"],
        t_mono=np.full(len(cat["t"]), np.nan),
        camera_index=cat["cam"],
        line=cat["line"],
    )
    return frames, videos


def _read_force(path: Path, params: dict, warnings: list[str]) -> logs.ForceLog:
    table = read_table(path, 2, warnings, "no force readings")
    t = floats(table, 0, warnings, "unix_time")
    value = floats(table, 1, warnings, "value")
    ok = finite_rows(table, {"unix_time": t, "value": value}, warnings)
    unit = str(params.get("force_unit", "g"))
    try:
        force_n = force_to_newtons(value[ok], unit)
    except ValueError as e:
        raise logs.RecordingError(
            f"{path.parent / logs.REF_PARAMS_FILE}: field 'force_unit': {e}"
        ) from None
    grams = value[ok] if unit == "g" else force_n / REFERENCE_G_TO_N  # as printed by the scale
    n = int(ok.sum())
    return logs.ForceLog(
        t[ok], np.full(n, np.nan), force_n, grams, np.full(n, -1, np.int64), table.lines[ok]
    )


def _read_printer(
    path: Path, centre: tuple[float, float], params: dict, warnings: list[str]
) -> logs.MoveLog:
    """Reference printer log: x, y are the press location; x = y = -1 marks non-data moves.

    Whether x, y are absolute printer coordinates or offsets from the sensor centre is
    decided from the data: if the G-code's own X/Y equal the logged x, y, they are
    absolute; otherwise if they lie within the press range around 0 they are offsets.
    """
    table = read_table(path, 4, warnings, "no printer commands", sep="\r")
    t = floats(table, 0, warnings, "unix_time")
    x = floats(table, 1, warnings, "x")
    y = floats(table, 2, warnings, "y")
    ok = finite_rows(table, {"unix_time": t, "x": x, "y": y}, warnings)
    table = table.select(ok)
    t, x, y = t[ok], x[ok], y[ok]
    gcode = [_command_block(r[3]) for r in table.rows]
    is_data = ~((x == REF_NON_DATA_XY) & (y == REF_NON_DATA_XY))
    absolute = _xy_is_absolute(x[is_data], y[is_data], gcode, is_data, params)
    xy = np.stack([x, y], axis=1)
    offset = xy - np.asarray(centre) if absolute else xy.copy()
    offset[~is_data] = np.nan
    xyz = np.full((len(t), 3), np.nan)
    absolute_xy = xy if absolute else xy + np.asarray(centre)
    xyz[:, :2] = np.where(is_data[:, None], absolute_xy, np.nan)
    press = _press_index(xy, is_data)
    return logs.MoveLog(t, np.full(len(t), np.nan), xyz, offset, is_data, press, gcode, table.lines)


def _command_block(text: str) -> str:
    """The G-code lines of one record, stripped, joined by ``\\n``."""
    return "\n".join(line.strip() for line in text.splitlines() if line.strip())


def _press_index(xy: np.ndarray, is_data: np.ndarray) -> np.ndarray:
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


def _xy_is_absolute(x, y, gcode, is_data, params) -> bool:
    data_gcode = [g for g, d in zip(gcode, is_data, strict=True) if d]
    for xi, yi, g in zip(x, y, data_gcode, strict=True):
        xy = gcode_xy(g)
        if xy is not None:
            return bool(
                abs(xy[0] - xi) <= GCODE_ROUNDING_MM and abs(xy[1] - yi) <= GCODE_ROUNDING_MM
            )
    if len(x) == 0:
        return False
    limit = float(params.get("radius", 13.75)) * OFFSET_RANGE_FACTOR
    near_zero = np.all(np.abs(x) <= limit) and np.all(np.abs(y) <= limit)
    return not near_zero
