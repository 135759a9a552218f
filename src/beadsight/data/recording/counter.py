"""The reference scale sketch's line counter in force logs: detect it, decode it.

The published Arduino sketch (``Scale_Reading.ino``) prints ``grams + 10000 * i`` with
``i`` cycling 0..9, and the reference logger writes that value as is, so a raw force
log reads 12.5, 10013.1, 20014.0, ... Taken as grams, every reading after the first
is 1 to 9 kg too high (up to ~900 N). The decoding rule is the one the project's
scale driver uses (:class:`beadsight.data.recording.scale_protocol.ReferenceDecoder`).

``mode``: ``"auto"`` decodes when the decoded counter steps through the 0..9 cycle
(+1 modulo 10 between most consecutive readings; a log without the counter decodes
to a constant counter), ``"on"`` always decodes, ``"off"`` never does (and warns if
the counter is there). What was found and done is returned for the QA file.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np

from beadsight.config import REFERENCE_G_TO_N
from beadsight.data.recording.logs import ForceLog
from beadsight.data.recording.scale_protocol import COUNTER_PERIOD, ReferenceDecoder

logger = logging.getLogger(__name__)

FORCE_COUNTER_MODES = ("auto", "on", "off")
CYCLE_FRACTION = 0.5  # detected when at least this share of steps are +1 (mod 10)
MIN_READINGS = 3  # fewer readings than this cannot show a cycle


def decode_counter(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """values: (M,) as printed by the sketch -> grams (M,) float64, counter (M,) int64 and
    lines lost before each reading (M,) int64 (a skipped counter value means lost lines)."""
    decoder = ReferenceDecoder()
    out = [decoder.decode(float(v)) for v in np.asarray(values, np.float64)]
    grams = np.array([o[0] for o in out], np.float64).reshape(-1)
    counter = np.array([o[1] for o in out], np.int64).reshape(-1)
    lost = np.array([o[2] for o in out], np.int64).reshape(-1)
    return grams, counter, lost


def cycle_fraction(counter: np.ndarray) -> float:
    """Share of consecutive readings whose counter steps by +1 modulo 10."""
    if len(counter) < 2:
        return 0.0
    steps = np.diff(counter) % COUNTER_PERIOD
    return float(np.mean(steps == 1))


def apply_force_counter(force: ForceLog, mode: str, name: str) -> tuple[ForceLog, dict[str, Any]]:
    """Decode the counter of ``force`` as ``mode`` says; returns the new log and a record.

    name: the force log's file name (for messages). The record holds mode, detected,
    decoded, cycle_fraction, lines_lost and a one-line message.
    """
    if mode not in FORCE_COUNTER_MODES:
        raise ValueError(f"force counter mode must be one of {FORCE_COUNTER_MODES}, got {mode!r}")
    grams, counter, lost = decode_counter(force.grams)
    fraction = cycle_fraction(counter)
    detected = len(force) >= MIN_READINGS and fraction >= CYCLE_FRACTION
    decode = mode == "on" or (mode == "auto" and detected)
    record: dict[str, Any] = {
        "mode": mode,
        "detected": bool(detected),
        "decoded": bool(decode),
        "cycle_fraction": round(fraction, 4),
        "lines_lost": int(lost.sum()) if decode else 0,
    }
    seen = f"{fraction:.0%} of consecutive values step through the 0..9 cycle"
    if decode:
        record["message"] = (
            f"{name}: decoded the reference sketch's +10000*i force counter ({seen}; "
            f"{record['lines_lost']} scale line(s) lost); --force-counter {mode}"
        )
        logger.info("%s", record["message"])
        force = replace(force, grams=grams, force_n=grams * REFERENCE_G_TO_N)
    elif detected:
        record["message"] = (
            f"{name}: values look like they carry the reference sketch's +10000*i counter "
            f"({seen}) but --force-counter off keeps them as they are"
        )
    else:
        record["message"] = f"{name}: no force counter ({seen}); values used as they are"
    return force, record
