"""Plausibility of a raw recording before it becomes a dataset. Never silent.

* **Absurd values** (a corrupted or forged log: ``1e308`` in a time field, ``1e300 g``)
  raise :class:`~beadsight.data.recording.RecordingError` naming the file and line,
  before anything is written.
* **Printer positions** beyond :data:`ABSURD_POSITION_MM`, or missing (NaN) where the
  finger is at a press (its position is the label), raise the same error.
* **Readings beyond the scale's capacity** (configurable) are reported with file and
  line, and the frames whose force would be interpolated from them are invalid.
* **Timestamps going backwards** in any log are reported with file and line.

Non-finite and unparsable values are reported (with their lines) by the readers,
which skip those rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beadsight.data.recording import Recording, RecordingError
from beadsight.data.recording.text import describe_lines

ABSURD_TIME_S = 1e10  # |timestamp| beyond this (year 2286 as unix time) is corruption
ABSURD_FORCE_N = 1e5  # ~10 tonnes: no tactile rig's scale reads this; a corrupted value
ABSURD_POSITION_MM = 1000.0  # a printer position a metre out: no rig reaches it; corruption
STREAMS = {"frames": "frame", "force": "force reading", "moves": "printer command"}


@dataclass
class Plausibility:
    """What :func:`check_recording` found. over_capacity: (M,) bool per force reading;
    warnings: one line each, naming file and lines."""

    over_capacity: np.ndarray
    warnings: list[str]

    def summary(self) -> dict:
        return {
            "readings_over_capacity": int(self.over_capacity.sum()),
            "warnings": list(self.warnings),
        }


def check_recording(rec: Recording, capacity_n: float) -> Plausibility:
    """Check ``rec``; raises RecordingError for absurd values (see the module docstring)."""
    for stream in STREAMS:
        _check_times(rec, stream)
    _check_positions(rec)
    force = rec.force.force_n
    absurd = np.flatnonzero(np.abs(force) > ABSURD_FORCE_N)
    if absurd.size:
        i = int(absurd[0])
        raise RecordingError(
            f"{rec.where('force', i)}: force reading {rec.force.grams[i]:g} g "
            f"({force[i]:.4g} N) is absurd (beyond {ABSURD_FORCE_N:g} N): the log is "
            f"corrupt; {absurd.size} such reading(s). Fix or remove those lines."
        )
    warnings = [w for stream in STREAMS if (w := _backwards(rec, stream))]
    over = np.abs(force) > capacity_n
    if over.any():
        i = int(np.argmax(np.abs(force)))
        lines = rec.force.line[over] if len(rec.force.line) == len(force) else []
        warnings.append(
            f"{rec.where('force', i)}: force {force[i]:.1f} N is beyond the scale's capacity "
            f"({capacity_n:g} N, --scale-capacity); {int(over.sum())} reading(s) above it "
            f"({describe_lines(lines) if len(lines) else 'see the log'}): frames whose force "
            "comes from them are invalid"
        )
    rec.warnings.extend(warnings)
    return Plausibility(over, warnings)


def _check_times(rec: Recording, stream: str) -> None:
    log = getattr(rec, stream)
    for clock in ("t_unix", "t_mono"):
        t = getattr(log, clock)
        bad = np.flatnonzero(np.isfinite(t) & (np.abs(t) > ABSURD_TIME_S))
        if bad.size:
            i = int(bad[0])
            raise RecordingError(
                f"{rec.where(stream, i)}: {STREAMS[stream]} time {clock}={t[i]:g} s is absurd "
                f"(beyond {ABSURD_TIME_S:g} s): the log is corrupt; {bad.size} such value(s). "
                "Fix or remove those lines."
            )


def _check_positions(rec: Recording) -> None:
    """RecordingError naming the line of an absurd printer position, or of a missing one
    at a press."""
    xyz, press = rec.moves.xyz_mm, rec.moves.press
    absurd = np.isfinite(xyz) & (np.abs(xyz) > ABSURD_POSITION_MM)
    missing = ~np.isfinite(xyz[:, :2]) & (press >= 0)[:, None]
    for bad, what in (
        (absurd, f"is absurd (beyond {ABSURD_POSITION_MM:g} mm)"),
        (missing, "is missing at a press (its position is the label)"),
    ):
        rows = np.flatnonzero(bad.any(axis=1))
        if rows.size:
            i = int(rows[0])
            raise RecordingError(
                f"{rec.where('moves', i)}: printer position {[float(v) for v in xyz[i]]} mm {what}: the log "
                f"is corrupt; {rows.size} such command(s). Fix or remove those lines."
            )


def _backwards(rec: Recording, stream: str) -> str | None:
    """A warning if the stream's timestamps go backwards in log order."""
    log = getattr(rec, stream)
    for clock in ("t_mono", "t_unix"):
        t = getattr(log, clock)
        ok = np.flatnonzero(np.isfinite(t))
        if ok.size < 2:
            continue
        back = ok[1:][np.diff(t[ok]) < 0]
        if back.size:
            i = int(back[0])
            return (
                f"{rec.where(stream, i)}: {STREAMS[stream]} time {clock} goes backwards "
                f"({back.size} time(s) in this log)"
            )
    return None
