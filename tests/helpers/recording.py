"""Synthetic raw recordings (both formats) with a known truth, for recording/process tests.

Each frame is a uniform grey whose level encodes its frame number, so a test can check
that dataset frame ``i`` is logged frame ``i`` after video decoding and preprocessing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from beadsight.config import REFERENCE_CENTRE_XY_MM
from beadsight.data.recording import RecordingWriter
from beadsight.devices.base import CommandRecord, ScaleReading

CENTRE = REFERENCE_CENTRE_XY_MM
T0_UNIX = 1.7e9
T0_MONO = 5000.0
G_TO_N = 9.81e-3


def frame_level(k: int) -> int:
    """Grey level of frame ``k`` (distinct for neighbouring frames, robust to JPEG)."""
    return 30 + (k * 11) % 190


@dataclass
class Timeline:
    """A press session: presses at ``xy`` (mm from centre) with trapezoid forces."""

    presses: int = 3
    fps: float = 30.0
    scale_hz: float = 80.0
    press_period_s: float = 2.0
    first_press_s: float = 0.5
    peak_n: tuple[float, ...] = (6.0, 9.0, 12.0, 7.0, 10.0, 8.0)
    force_start_s: float = 0.1  # the scale log starts a little after the camera

    @property
    def xy(self) -> np.ndarray:
        rng = np.random.default_rng(7)
        return rng.uniform(-10, 10, size=(self.presses, 2))

    @property
    def end_s(self) -> float:
        return self.first_press_s + self.presses * self.press_period_s + 0.3

    def force_n(self, t: np.ndarray) -> np.ndarray:
        """Trapezoid per press: ramps 0.25 s, plateau 0.5 s, starting 0.5 s into the press."""
        t = np.asarray(t, np.float64)
        out = np.zeros_like(t)
        for k in range(self.presses):
            s = self.first_press_s + k * self.press_period_s + 0.5
            ramp = np.clip((t - s) / 0.25, 0, 1) * np.clip((s + 1.0 - t) / 0.25, 0, 1)
            out += ramp * self.peak_n[k % len(self.peak_n)]
        return out

    def commands(self) -> list[tuple[float, str, float, float, float, int]]:
        """(t_s, gcode, x, y, z, press) in time order; press -1 = not a data move."""
        cx, cy = CENTRE
        cmds = [(0.2, "G28", 0.0, 0.0, 0.0, -1), (0.3, "G1 Z137.5 F700", 0.0, 0.0, 137.5, -1)]
        for k, (dx, dy) in enumerate(self.xy):
            t = self.first_press_s + k * self.press_period_s
            x, y = cx + dx, cy + dy
            cmds += [
                (t, f"G1 X{x:.3f} Y{y:.3f} F700", x, y, 137.5, k),
                (t + 0.3, "G1 Z127.5 F200", x, y, 127.5, k),
                (t + 1.6, "G1 Z137.5 F700", x, y, 137.5, k),
            ]
        cmds.append((self.end_s - 0.1, f"G1 X{cx:.3f} Y{cy + 30:.3f} F700", cx, cy + 30, 137.5, -1))
        return cmds

    def frame_times(self) -> np.ndarray:
        return np.arange(0, self.end_s, 1.0 / self.fps)

    def force_times(self) -> np.ndarray:
        return np.arange(self.force_start_s, self.end_s - 0.05, 1.0 / self.scale_hz)

    def position_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Expected zero-order hold: (N, 2) mm offsets and (N,) data flag."""
        cmds = self.commands()
        times = np.array([c[0] for c in cmds])
        idx = np.searchsorted(times, t, side="right") - 1
        pos = np.full((len(t), 2), np.nan)
        data = np.zeros(len(t), bool)
        for i, j in enumerate(idx):
            if j >= 0 and cmds[j][5] >= 0:
                pos[i] = (cmds[j][2] - CENTRE[0], cmds[j][3] - CENTRE[1])
                data[i] = True
        return pos, data


def write_beadsight_raw(
    path: Path, tl: Timeline, frame_hw=(96, 120), chunk_frames=30, drop_frames: tuple[int, ...] = ()
) -> Path:
    """A raw session in this project's format, written through RecordingWriter."""
    meta = {"virtual": True, "centre_xy_mm": list(CENTRE), "plan": {"presses": tl.presses}}
    events = []
    with RecordingWriter(path, meta, frame_hw=frame_hw, fps=tl.fps, chunk_frames=chunk_frames) as w:
        f_times = tl.force_times()
        grams = tl.force_n(f_times) / G_TO_N
        cmds = tl.commands()
        ci = fi = 0
        for k, t in enumerate(tl.frame_times()):
            while fi < len(f_times) and f_times[fi] <= t:
                w.write_readings(
                    [
                        ScaleReading(
                            T0_UNIX + f_times[fi],
                            T0_MONO + f_times[fi],
                            round(float(grams[fi]), 2),
                            grams[fi] * G_TO_N,
                            fi,
                            None,
                        )
                    ]
                )
                fi += 1
            while ci < len(cmds) and cmds[ci][0] <= t:
                tc, gcode, x, y, z, press = cmds[ci]
                w.write_command(CommandRecord(T0_UNIX + tc, T0_MONO + tc, gcode, x, y, z), press)
                if gcode.startswith("G1 X") and press >= 0:
                    events.append(w.log_event("press_start", press=press))
                ci += 1
            if k in drop_frames:
                continue
            image = np.full((*frame_hw, 3), frame_level(k), np.uint8)
            w.write_frame(image, t_unix=T0_UNIX + t, t_mono=T0_MONO + t, camera_index=k)
        for k in range(tl.presses):
            w.log_event("press_end", press=k)
    return path


def write_reference_raw(
    path: Path,
    tl: Timeline,
    frame_hw=(96, 120),
    videos=2,
    absolute_xy: bool = False,
    fourcc: str = "XVID",
    counter: bool = False,
    command_blocks: bool = False,
) -> Path:
    """A raw session in the reference format (XVID videos, text logs).

    counter: force values as the reference sketch (Scale_Reading.ino) prints them,
    ``grams + 10000 * i`` with ``i`` cycling 0..9 line by line. command_blocks: the
    genuine printer log record format, one ``\r``-terminated record per command block
    (all G-code lines of a press in one record, separated by ``\n``).
    """
    path.mkdir(parents=True, exist_ok=True)
    times = tl.frame_times()
    per = int(np.ceil(len(times) / videos))
    h, w = frame_hw
    for v in range(videos):
        video = path / f"video_{v}.avi"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*fourcc), tl.fps, (w, h))
        lines = []
        for k in range(v * per, min(len(times), (v + 1) * per)):
            writer.write(np.full((h, w, 3), frame_level(k), np.uint8))
            lines.append(f"{float(T0_UNIX + times[k])!r},{k},{video}\n")
        writer.release()
        (path / f"video_log_{v}.txt").write_text("".join(lines))
    ft = tl.force_times()
    grams = tl.force_n(ft) / G_TO_N
    values = [g + 10000 * (k % 10) if counter else g for k, g in enumerate(grams)]
    (path / "force_log.txt").write_text(
        "".join(f"{float(T0_UNIX + t)!r},{v:.2f}\n" for t, v in zip(ft, values, strict=True))
    )
    records = []
    for t, gcode, x, y, _z, press in tl.commands():
        if press < 0:
            lx = ly = -1.0
        elif absolute_xy:
            lx, ly = x, y
        else:
            lx, ly = x - CENTRE[0], y - CENTRE[1]
        if command_blocks and records and press >= 0 and records[-1][3] == press:
            records[-1][4].append(gcode)  # the rest of the press's block
            continue
        records.append([float(T0_UNIX + t), lx, ly, press, [gcode]])
    text = "".join(f"{t!r},{lx},{ly},{chr(10).join(block)}\r" for t, lx, ly, _, block in records)
    (path / "printer_log.txt").write_text(text, newline="")
    params = {
        "resolution": [w, h],
        "fps": tl.fps,
        "contact_radius": 6.25,
        "sensor_size": [41, 41],
        "force_unit": "g",
        "dist_unit": "mm",
        "center": list(CENTRE),
        "radius": 13.75,
    }
    (path / "experiment_parameters.json").write_text(json.dumps(params))
    return path
