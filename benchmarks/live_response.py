"""How a live recording on the simulator follows the true force: lag, repeats, error.

    beadsight live --source sim --no-viewer --output rec.h5 --duration 120
    PYTHONPATH=src .venv/bin/python benchmarks/live_response.py rec.h5 [--json]

Reads a ``live --output`` readings file made on the simulator (it holds the simulator's
true force of each reading's frame, ``reference_force_n``) and reports, over the presses
in it (a press: the true force from above the 10 g release force back down to it):

* onset lag: frame time from the true force's first 1 N crossing to the reading's, and
  release lag: from the true force's last fall below 1 N to the reading's fall below 1 N
  that lasts (it stays below for 0.3 s; a reading over 1 N later, while unloaded, is
  counted in ``unloaded_over_1n_pct``: readings of 1 N or more at a true 0 N) (median, max;
  ms of capture time, so the camera rate sets the resolution; the processing latency,
  capture to reading, is reported apart as ``latency_ms_median``);
* the share of in-contact readings (true force > 2 N) whose force repeats the previous
  reading's exactly (a latched or duplicated reading);
* the force error over in-contact readings, ``100 sum |F - F_true| / sum F_true`` (the
  paper's total-force error, on these readings).

A press's readings are looked at from 0.5 s before its true force leaves the release
force to 0.5 s before the next press's do. Presses where the true force never reaches 1 N
are left out; presses where the reading never crosses 1 N are counted as ``missed``. The last line is a JSON object (--json: the
only line).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from beadsight.config import ContactThresholds

CROSSING_N = 1.0  # the force whose crossings time onset and release, N
IN_CONTACT_N = 2.0  # readings with a true force above this count as in contact (paper: CoP)
LOOK_BEFORE_S = 0.5  # a reading may cross this long before the true force does
RELEASED_S = 0.3  # the reading has fallen once it stays below 1 N this long


def press_spans(true_n: np.ndarray) -> list[tuple[int, int]]:
    """(first, end) reading indices of each press: the true force above the release force,
    from the first such reading to the next reading at or below it."""
    above = true_n > ContactThresholds().release_n
    edges = np.flatnonzero(np.diff(np.concatenate([[0], above.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def response(t_s: np.ndarray, force_n: np.ndarray, true_n: np.ndarray, latency_s: np.ndarray):
    """The figures of the module docstring from per-reading capture times (s), published
    and true forces (N) and latencies (s); a dict of plain numbers (None where none)."""
    spans = press_spans(true_n)
    onset, release, missed = [], [], 0
    bounds = [0] + [end for _, end in spans]
    for k, (first, end) in enumerate(spans):
        up = np.flatnonzero(true_n[first:end] >= CROSSING_N)
        if not len(up):
            continue
        true_on, true_off = first + up[0], first + up[-1] + 1
        lo = max(bounds[k], _index(t_s, t_s[first] - LOOK_BEFORE_S))
        # up to where the next press's onset is looked for
        hi = _index(t_s, t_s[spans[k + 1][0]] - LOOK_BEFORE_S) if k + 1 < len(spans) else len(t_s)
        read = np.flatnonzero(force_n[lo:hi] >= CROSSING_N)
        if not len(read):
            missed += 1
            continue
        read_on = lo + read[0]
        onset.append(t_s[read_on] - t_s[true_on])
        read_off = _released(t_s, force_n, read_on, hi)
        if read_off is not None and true_off < len(t_s):
            release.append(t_s[read_off] - t_s[true_off])
    unloaded = true_n == 0
    false_pct = 100 * float((force_n[unloaded] >= CROSSING_N).mean()) if unloaded.any() else None
    contact = np.flatnonzero(true_n > IN_CONTACT_N)
    contact = contact[contact > 0]
    repeats = force_n[contact] == force_n[contact - 1]
    error = np.abs(force_n[contact] - true_n[contact]).sum() / max(true_n[contact].sum(), 1e-12)
    return {
        "presses": len(spans),
        "missed": missed,
        "onset_lag_ms_median": _ms(np.median(onset)) if onset else None,
        "onset_lag_ms_max": _ms(np.max(onset)) if onset else None,
        "release_lag_ms_median": _ms(np.median(release)) if release else None,
        "release_lag_ms_max": _ms(np.max(release)) if release else None,
        "in_contact_readings": len(contact),
        "repeated_pct": round(100 * float(repeats.mean()), 2) if len(contact) else None,
        "force_error_pct": round(100 * float(error), 2) if len(contact) else None,
        "unloaded_over_1n_pct": round(false_pct, 2) if false_pct is not None else None,
        "latency_ms_median": _ms(np.median(latency_s)) if len(latency_s) else None,
    }


def _released(t_s: np.ndarray, force_n: np.ndarray, start: int, end: int) -> int | None:
    """The first reading in [start, end) from which the reading stays below 1 N for
    RELEASED_S (or to ``end``); None if there is none."""
    below = force_n[start:end] < CROSSING_N
    for i in np.flatnonzero(below):
        k = start + i
        stop = min(_index(t_s, t_s[k] + RELEASED_S), end)
        if below[i : stop - start].all():
            return int(k)
    return None


def _index(t_s: np.ndarray, at_s: float) -> int:
    """The first reading at or after ``at_s``."""
    return int(np.searchsorted(t_s, at_s))


def _ms(seconds: float) -> float:
    return round(1000.0 * float(seconds), 1)


def main() -> None:
    from beadsight.live.recording.readings import open_readings

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("recording", type=Path, help="a live --output readings file (.h5) of the sim")
    p.add_argument("--json", action="store_true", help="print only the JSON object")
    args = p.parse_args()
    with open_readings(args.recording) as rf:
        true = rf.reference_force_n.astype(np.float64)
        if not np.isfinite(true).any():
            raise SystemExit(f"{args.recording}: no true force (record on the simulator)")
        figures = response(
            rf.timestamp_s, rf.force_n.astype(np.float64), true, rf.latency_s.astype(np.float64)
        )
        figures = {"readings": len(rf), "checkpoint": rf.provenance.get("checkpoint"), **figures}
        seconds = float(rf.timestamp_s[-1] - rf.timestamp_s[0]) if len(rf) else 0.0
        figures["readings_per_s"] = round(len(rf) / seconds, 2) if seconds > 0 else None
    if not args.json:
        for name, value in figures.items():
            print(f"{name:24s} {value}")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
