"""Reading this project's raw session folder (``docs/recording-format.md``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from beadsight.config import REFERENCE_CENTRE_XY_MM, REFERENCE_G_TO_N
from beadsight.data.recording import logs
from beadsight.data.recording.text import (
    finite_rows,
    floats,
    json_lines,
    parse_rows,
    read_json,
    read_records,
    read_table,
)
from beadsight.data.recording.video import probe_video


def _metadata(path: Path, warnings: list[str]) -> dict:
    meta_path = path / logs.SESSION_FILE
    metadata = read_json(meta_path) if meta_path.exists() else {}
    if not metadata:
        warnings.append(f"{logs.SESSION_FILE} missing; using defaults")
    fmt = metadata.get("format", logs.RAW_FORMAT)
    if fmt != logs.RAW_FORMAT:
        raise logs.RecordingError(
            f"{meta_path}: field 'format' is {fmt!r}, expected {logs.RAW_FORMAT!r}"
        )
    if int(metadata.get("format_version", 1)) > logs.RAW_FORMAT_VERSION:
        raise logs.RecordingError(
            f"{meta_path}: format_version {metadata['format_version']} is newer than this "
            f"beadsight reads ({logs.RAW_FORMAT_VERSION}); upgrade beadsight"
        )
    status = metadata.get("status")
    if status not in (None, "complete"):
        warnings.append(f"session status is {status!r} (not 'complete')")
    return metadata


def open_ours(path: Path) -> logs.Recording:
    """Read a beadsight raw session folder (videos stay on disk)."""
    warnings: list[str] = []
    metadata = _metadata(path, warnings)
    frames = _read_frames(path / logs.FRAMES_FILE, warnings)
    centre = tuple(float(v) for v in metadata.get("centre_xy_mm", REFERENCE_CENTRE_XY_MM))
    force = _read_force(path / logs.FORCE_FILE, warnings)
    moves = _read_printer(path / logs.PRINTER_FILE, centre, warnings)
    events = json_lines(path / logs.EVENTS_FILE, warnings)
    videos = {
        int(m.group(1)): p
        for p in sorted(path.glob("video_*.avi"))
        if (m := logs.VIDEO_PATTERN.fullmatch(p.name))
    }
    camera = metadata.get("camera", {})
    fps = float(camera.get("fps") or logs.DEFAULT_FPS)  # host frame rate (virtual rigs: scaled)
    frame_hw = None
    if camera.get("height") and camera.get("width"):
        frame_hw = (int(camera["height"]), int(camera["width"]))
    elif videos:
        frame_hw = probe_video(next(iter(videos.values())))[0]
    files = {"frames": logs.FRAMES_FILE, "force": logs.FORCE_FILE, "moves": logs.PRINTER_FILE}
    return logs.Recording(
        path,
        logs.RAW_FORMAT,
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
        files,
    )


def _read_frames(path: Path, warnings: list[str]) -> logs.FrameLog:
    if not path.exists():
        raise logs.RecordingError(f"{path}: frame log not found")
    table = parse_rows(path, read_records(path, "\n", warnings), 5, warnings, logs.FRAMES_COLUMNS)
    f = {name: floats(table, k, warnings, name) for k, name in enumerate(logs.FRAMES_COLUMNS)}
    ok = finite_rows(table, {k: f[k] for k in ("chunk", "index", "t_unix")}, warnings)
    cam = f["camera_index"][ok]
    return logs.FrameLog(
        chunk=f["chunk"][ok].astype(np.int32),
        index=f["index"][ok].astype(np.int32),
        t_unix=f["t_unix"][ok],
        t_mono=f["t_mono"][ok],
        camera_index=np.where(np.isfinite(cam), cam, -1).astype(np.int64),
        line=table.lines[ok],
    )


def _read_force(path: Path, warnings: list[str]) -> logs.ForceLog:
    table = read_table(
        path, len(logs.FORCE_COLUMNS), warnings, "no force readings", header=logs.FORCE_COLUMNS
    )
    f = {name: floats(table, k, warnings, name) for k, name in enumerate(logs.FORCE_COLUMNS[:4])}
    ok = finite_rows(table, {k: f[k] for k in ("t_unix", "grams")}, warnings)
    seq = f["seq"][ok]
    return logs.ForceLog(
        t_unix=f["t_unix"][ok],
        t_mono=f["t_mono"][ok],
        force_n=f["grams"][ok] * REFERENCE_G_TO_N,
        grams=f["grams"][ok],
        seq=np.where(np.isfinite(seq), seq, -1).astype(np.int64),
        line=table.lines[ok],
    )


def _read_printer(path: Path, centre: tuple[float, float], warnings: list[str]) -> logs.MoveLog:
    # gcode (3rd column) has no commas: split on all of them
    table = read_table(
        path,
        len(logs.PRINTER_COLUMNS),
        warnings,
        "no printer commands",
        header=logs.PRINTER_COLUMNS,
        split_all=True,
    )
    t_unix, t_mono = (floats(table, k, warnings, logs.PRINTER_COLUMNS[k]) for k in range(2))
    xyz = np.stack([floats(table, k, warnings, logs.PRINTER_COLUMNS[k]) for k in (3, 4, 5)], axis=1)
    xyz = xyz.reshape(-1, 3)
    press = floats(table, 6, warnings, "press")
    ok = finite_rows(table, {"t_unix": t_unix}, warnings)
    press = np.where(np.isfinite(press), press, -1).astype(np.int64)[ok]
    xyz = xyz[ok]
    is_data = (press >= 0) & np.isfinite(xyz[:, :2]).all(axis=1)
    return logs.MoveLog(
        t_unix=t_unix[ok],
        t_mono=t_mono[ok],
        xyz_mm=xyz,
        offset_mm=xyz[:, :2] - np.asarray(centre),
        is_data=is_data,
        press=press,
        gcode=[r[2] for r, keep in zip(table.rows, ok, strict=True) if keep],
        line=table.lines[ok],
    )
