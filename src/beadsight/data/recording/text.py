"""Reading the text logs of a raw session: records, fields, numbers, JSON.

A log written as data arrives may end in a torn record (a crash mid-write); it is
dropped and reported. Every kept row carries the number of the line (record) it
came from, and every problem is reported with the file and the lines it affects.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.data.recording.logs import EVENTS_FILE, SESSION_FILE, RecordingError
from beadsight.files import read_bounded, read_json_object

LINES_SHOWN = 3  # line numbers quoted in one warning before "and N more"
MAX_LOG_BYTES = 1 << 30  # a text log beyond 1 GiB (days of 80 Hz force readings) is refused
MAX_RECORD_CHARS = 64 * 1024  # one log record (line) beyond this is corruption


@dataclass
class Table:
    """The rows of a delimited log. rows: fields of each row; lines: (R,) int64 1-based
    line (record) number of each row in ``path``."""

    path: Path
    rows: list[list[str]]
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)

    def select(self, keep: np.ndarray) -> Table:
        rows = [r for r, k in zip(self.rows, keep, strict=True) if k]
        return Table(self.path, rows, self.lines[keep])


def describe_lines(lines: Sequence[int] | np.ndarray) -> str:
    """``"line 4"``, ``"lines 4, 9, 12"`` or ``"lines 4, 9, 12 and 30 more"``."""
    lines = [int(v) for v in lines]
    if len(lines) == 1:
        return f"line {lines[0]}"
    shown = ", ".join(str(v) for v in lines[:LINES_SHOWN])
    more = len(lines) - LINES_SHOWN
    return f"lines {shown}" + (f" and {more} more" if more > 0 else "")


def read_records(path: Path, sep: str, warnings: list[str]) -> list[tuple[int, str]]:
    """(record number, text) of the non-blank records of ``path``.

    ``sep="\\n"``: one record per line (``\\r\\n`` tolerated). ``sep="\\r"``: records end
    with ``\\r`` and may contain ``\\n`` (the reference printer log); a file with no
    ``\\r`` at all is read line by line. A last record without its terminator is
    dropped as truncated (a crash mid-write) and reported.
    """
    data = read_bounded(path, MAX_LOG_BYTES, RecordingError, "a text log").decode(
        "utf-8", errors="replace"
    )
    if sep == "\r" and "\r" not in data:
        sep = "\n"
    records = data.split(sep)
    long = next((k for k, r in enumerate(records) if len(r) > MAX_RECORD_CHARS), None)
    if long is not None:
        raise RecordingError(
            f"{path} line {long + 1}: {len(records[long])} characters, more than "
            f"{MAX_RECORD_CHARS} for one record (a corrupt log?)"
        )
    tail = records.pop()  # text after the last terminator: '' when complete
    if tail.strip():
        warnings.append(
            f"{path.name}: last record is truncated (line {len(records) + 1}: "
            f"{tail[:40]!r}); dropped"
        )
    return [(k + 1, r) for k, r in enumerate(records) if r.strip()]


def parse_rows(
    path: Path,
    records: Sequence[tuple[int, str]],
    ncols: int,
    warnings: list[str],
    header: tuple[str, ...] | None = None,
    *,
    split_all: bool = False,
) -> Table:
    """Split CSV records into ``ncols`` fields (the last field may contain commas, unless
    ``split_all``); a first record starting with ``header[0]`` is skipped."""
    rows, lines, bad = [], [], []
    for k, (line, rec) in enumerate(records):
        text = rec.strip()
        parts = text.split(",") if split_all else text.split(",", ncols - 1)
        if k == 0 and header is not None and parts and parts[0] == header[0]:
            continue
        if len(parts) != ncols:
            bad.append(line)
            continue
        rows.append(parts)
        lines.append(line)
    if bad:
        warnings.append(
            f"{path.name}: skipped {len(bad)} malformed line(s) (expected {ncols} fields): "
            f"{describe_lines(bad)}"
        )
    return Table(path, rows, np.asarray(lines, np.int64))


def read_table(
    path: Path,
    ncols: int,
    warnings: list[str],
    missing: str,
    *,
    sep: str = "\n",
    header: tuple[str, ...] | None = None,
    split_all: bool = False,
) -> Table:
    """:func:`parse_rows` of a log file; an absent file is an empty table and the warning
    ``"<name> missing: <missing>"``."""
    if not path.exists():
        warnings.append(f"{path.name} missing: {missing}")
        return Table(path, [], np.zeros(0, np.int64))
    records = read_records(path, sep, warnings)
    return parse_rows(path, records, ncols, warnings, header, split_all=split_all)


def floats(table: Table, col: int, warnings: list[str], name: str | None = None) -> np.ndarray:
    """Column ``col`` as float64: an empty field is NaN (not recorded); text that is not a
    number is NaN and reported with its lines."""
    out = np.empty(len(table), dtype=np.float64)
    bad = []
    for i, r in enumerate(table.rows):
        text = r[col].strip()
        try:
            out[i] = float(text) if text else math.nan
        except ValueError:
            out[i] = math.nan
            bad.append(int(table.lines[i]))
    if bad:
        label = f"field {name!r}" if name else f"column {col + 1}"
        warnings.append(
            f"{table.path.name}: {len(bad)} unparsable number(s) in {label}: {describe_lines(bad)}"
        )
    return out


def finite_rows(table: Table, values: dict[str, np.ndarray], warnings: list[str]) -> np.ndarray:
    """(R,) bool: rows where every array of ``values`` is finite. The rows dropped because a
    value is NaN or infinite are reported with their lines (unparsable text was already
    reported by :func:`floats`)."""
    ok = np.ones(len(table), bool)
    for name, v in values.items():
        bad = ~np.isfinite(v)
        if bad.any():
            texts = [table.rows[i] for i in np.flatnonzero(bad)[:1]]
            warnings.append(
                f"{table.path.name}: {int(bad.sum())} row(s) whose field {name!r} is not a "
                f"finite number skipped: {describe_lines(table.lines[bad])} (e.g. "
                f"{','.join(texts[0])!r})"
            )
        ok &= ~bad
    return ok


def json_lines(path: Path, warnings: list[str]) -> list[dict[str, Any]]:
    """The JSON objects of a JSON-lines file (bad lines skipped and reported)."""
    if not path.exists():
        return []
    out = []
    for line, rec in read_records(path, "\n", warnings):
        try:
            obj = json.loads(rec)
        except json.JSONDecodeError:
            warnings.append(f"{path.name}: line {line} is not valid JSON; skipped")
            continue
        if isinstance(obj, dict):
            out.append(obj)
    return out


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object file; RecordingError naming the file if it is not one."""
    return read_json_object(path, RecordingError)


def read_session(path: str | Path) -> dict[str, Any]:
    """The ``session.json`` of a recording folder (RecordingError if missing or malformed)."""
    meta = Path(path) / SESSION_FILE
    if not meta.exists():
        raise RecordingError(f"{meta}: not found (not a beadsight raw recording?)")
    return read_json(meta)


def read_events(path: str | Path) -> list[dict[str, Any]]:
    """The events of a recording folder, oldest first (a torn last line is skipped)."""
    return json_lines(Path(path) / EVENTS_FILE, [])
