"""The two line formats an HX711 scale may speak, as pure functions (no I/O).

**beadsight firmware** (``firmware/scale/scale.ino``, 57600 baud, lines end ``\\r\\n``)::

    I,beadsight-scale,<version>,rate_hz=<hz>,factor=<counts per gram>   boot line and '?' reply
    R,<seq>,<device_ms>,<grams>      one reading: seq counts from 0 at boot, device_ms is
                                     the Arduino's millis() when sampled, grams has 2 decimals
    OK T | OK C <factor> | OK S <hz> replies to the commands T, C <grams>, S <hz>
    ERR <text>                       a command was refused
    # <text>                         a comment (ignored)

**reference sketch** (the published rig's Arduino code, 57600 baud): ``start`` once after
taring at boot, then one value per line with 2 decimals, ``value = grams + 10000 * i``
where ``i`` counts 0, 1, ..., 9, 0, ... so that consecutive lines always differ.

Decoding the reference counter (:class:`ReferenceDecoder`): with ``p`` the previous decoded
grams (0 at start and after ``start``), the decoded reading is the value congruent to
``v`` modulo 10000 that lies nearest to ``p``::

    k = floor((v - p) / 10000 + 1/2);   grams = v - 10000 * k;   i = k mod 10

(ties go to the larger ``grams``). This is exact as long as the load changes by less than
5000 g between consecutive lines, far beyond what the rig's load cell sees (the tare at
boot makes the first reading about 0). The counter then detects dropped lines: after
``i_prev``, a line with counter ``i`` means ``(i - i_prev - 1) mod 10`` lines were lost
(up to 9 in a row are detected). Counter checks start once the counter has been seen to
change, so a plain sketch printing grams without a counter (``i`` always 0) decodes the
same and reports no drops. The reference's own reader instead took ``v mod 10000`` and
mapped values above 9000 to negative ones (readings limited to (-1000, 9000] g).

**Telling them apart** (:class:`ProtocolDetector`): a beadsight line (``R,...``,
``I,beadsight-scale,...``) decides at once, so does the reference sketch's ``start``.
Plain numbers decide for the reference sketch only after ``DETECT_NUMBER_LINES`` of them
in a row, and the first of them is dropped: a board that does not reset when the port
opens is joined mid-line, and the tail of ``R,12,3456,1.23`` reads as the number ``1.23``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")

FIRMWARE_NAME = "beadsight-scale"
FIRMWARE_VERSION = "1.0.0"
COUNTER_STEP_G = 10000.0  # the reference sketch adds this times its counter
COUNTER_PERIOD = 10  # the reference counter runs 0..9
REFERENCE_COUNTS_PER_GRAM = 545654.0 / 1175.0  # the reference sketch's calibration, ~464.4
SUPPORTED_RATES_HZ = (10, 80)  # the HX711's two output data rates (RATE pin low / high)
DETECT_NUMBER_LINES = 3  # plain-number lines in a row that identify the reference sketch


@dataclass(frozen=True)
class Sample:
    """One decoded reading before host timestamps: grams, sequence number, device ms."""

    grams: float
    seq: int | None
    device_ms: int | None


@dataclass(frozen=True)
class DeviceInfo:
    """What the beadsight firmware says about itself (boot line, ``?``)."""

    firmware: str
    version: str
    rate_hz: float | None = None
    factor: float | None = None  # calibration, ADC counts per gram
    extra: dict[str, str] = field(default_factory=dict)


# --- beadsight firmware ---------------------------------------------------------------------
def format_reading(seq: int, device_ms: int, grams: float) -> str:
    return f"R,{seq},{device_ms},{grams:.2f}"


def format_info(version: str, rate_hz: float, factor: float) -> str:
    return f"I,{FIRMWARE_NAME},{version},rate_hz={rate_hz:g},factor={factor:.2f}"


def parse_reading(line: str) -> Sample:
    """``R,<seq>,<ms>,<grams>`` -> Sample; ValueError if malformed."""
    parts = line.split(",")
    if len(parts) != 4 or parts[0] != "R":
        raise ValueError(f"not a reading line: {line!r}")
    seq, device_ms, grams = int(parts[1]), int(parts[2]), float(parts[3])
    if seq < 0 or device_ms < 0 or not math.isfinite(grams):
        raise ValueError(f"reading out of range: {line!r}")
    return Sample(grams=grams, seq=seq, device_ms=device_ms)


def parse_info(line: str) -> DeviceInfo:
    """``I,<firmware>,<version>,key=value,...`` -> DeviceInfo; ValueError if malformed."""
    parts = line.split(",")
    if len(parts) < 3 or parts[0] != "I":
        raise ValueError(f"not an info line: {line!r}")
    extra = {}
    for item in parts[3:]:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"info field {item!r} is not key=value in {line!r}")
        extra[key.strip()] = value.strip()
    rate = float(extra.pop("rate_hz")) if "rate_hz" in extra else None
    factor = float(extra.pop("factor")) if "factor" in extra else None
    return DeviceInfo(firmware=parts[1], version=parts[2], rate_hz=rate, factor=factor, extra=extra)


# --- reference sketch ------------------------------------------------------------------------
def parse_reference_value(line: str) -> float:
    """One reference line -> its float value; ValueError if it is not a plain number."""
    text = line.strip()
    if not text or any(c not in "0123456789.-+" for c in text):
        raise ValueError(f"not a number line: {line!r}")
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"not a finite number: {line!r}")
    return value


def encode_reference_value(grams: float, counter: int) -> float:
    """What the reference sketch prints for ``grams`` at counter ``counter`` (0..9)."""
    return grams + COUNTER_STEP_G * (counter % COUNTER_PERIOD)


class ReferenceDecoder:
    """Undo the reference sketch's +10000*i counter; see the module docstring."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the history (the device rebooted and tared)."""
        self.previous_grams = 0.0
        self.previous_counter: int | None = None
        self.counter_active = False  # the counter has been seen to change

    def decode(self, value: float) -> tuple[float, int, int]:
        """``(grams, counter, lines_lost)`` for one line's value."""
        k = math.floor((value - self.previous_grams) / COUNTER_STEP_G + 0.5)
        grams = round(value - COUNTER_STEP_G * k, 2)
        counter = k % COUNTER_PERIOD
        lost = 0
        if self.previous_counter is not None:
            if counter != self.previous_counter:
                self.counter_active = True
            if self.counter_active:
                lost = (counter - self.previous_counter - 1) % COUNTER_PERIOD
        self.previous_grams = grams
        self.previous_counter = counter
        return grams, counter, lost


# --- detection ---------------------------------------------------------------------------------
def line_kind(line: str) -> str | None:
    """'beadsight' or 'reference' for a line only that protocol sends, 'number' for a plain
    number (the reference sketch, or the tail of a beadsight line), None for garbage."""
    if line.startswith("R,") or line.startswith(f"I,{FIRMWARE_NAME}"):
        return "beadsight"
    if line.strip().lower() == "start":
        return "reference"
    try:
        parse_reference_value(line)
    except ValueError:
        return None
    return "number"


class ProtocolDetector(Generic[T]):
    """Decides the protocol from the first lines; see the module docstring."""

    def __init__(self, number_lines: int = DETECT_NUMBER_LINES) -> None:
        self.number_lines = int(number_lines)
        self.pending: list[tuple[str, T]] = []  # number lines seen so far, with their items
        self.dropped: str | None = None  # the number line dropped once decided (maybe partial)

    def feed(self, line: str, item: T) -> tuple[str | None, list[T]]:
        """``(protocol, items to handle with it)`` once decided, else ``(None, [])``.

        item: what to hand back for this line (e.g. the line with its timestamps).
        Raises ValueError for a line neither protocol sends.
        """
        kind = line_kind(line)
        if kind is None:
            raise ValueError(f"not a scale line: {line!r}")
        if kind == "number":
            self.pending.append((line, item))
            if len(self.pending) < self.number_lines:
                return None, []
            kind, items = "reference", [it for _, it in self.pending[1:]]
        else:
            items = [item]
        self.dropped = self.pending[0][0] if self.pending else None
        self.pending = []
        return kind, items
