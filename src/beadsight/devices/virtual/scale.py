"""A virtual HX711 scale on a pseudo-terminal: the beadsight firmware or the reference sketch.

It behaves like the Arduino: opening the port reboots it; after ``boot_delay_s`` it tares
and announces itself (``I,beadsight-scale,...`` or ``start``), then streams one reading
per sample period (``rate_hz``: 10 or 80, simulated time) with Gaussian noise and a
linear drift. ``reset_on_open=False`` models a board that does not reset (auto-reset
disabled, or a USB adapter without DTR): it has been streaming all along, so the host
joins mid-line and the first line it reads is the tail of a reading (``"1.23"``). The load comes from ``load_g`` or from a force source (the rig's world:
``force_fn(t_sim) -> newtons``).

The load cell is modelled in ADC counts: ``counts = true_counts_per_gram * (load + drift +
noise)``; the firmware reports ``(counts - tare_counts) / factor``, where ``factor``
starts at ``true_counts_per_gram * (1 + factor_error)`` and is set by ``C <grams>``.

Faults (thread-safe): :meth:`emit_garbage`, :meth:`stop_streaming` /
:meth:`resume_streaming`, :meth:`drop_next`, :meth:`ignore_commands`, :meth:`unplug`.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

import numpy as np

from beadsight.data.recording.scale_protocol import (
    FIRMWARE_VERSION,
    REFERENCE_COUNTS_PER_GRAM,
    SUPPORTED_RATES_HZ,
    encode_reference_value,
    format_info,
    format_reading,
)
from beadsight.devices.clock import SimClock
from beadsight.devices.virtual.pty_device import PtyDevice
from beadsight.geometry import newtons_to_grams

logger = logging.getLogger(__name__)

BOOT_DELAY_S = 0.2  # reset -> first line (a real Arduino takes ~1.6 s)
NOISE_G = 0.05  # standard deviation of one reading, g (HX711 at 10 Hz on a 5 kg cell)
TARE_SAMPLES = 10  # readings the firmware averages for T and C
REFERENCE_RATE_HZ = 10.0  # the reference sketch runs the HX711 at its default rate
MIN_NET_COUNTS = 100  # like the firmware: C refuses a load smaller than this (~0.2 g)
MAX_BURST = 1000  # readings emitted in one tick at most (after a long host stall)
PARTIAL_CHARS = 4  # a host joining mid-line first reads this many last characters of a line


class VirtualScale(PtyDevice):
    """Virtual HX711 scale; open :attr:`port` with :class:`~beadsight.devices.hx711.HX711Scale`.

    protocol: "beadsight" (our firmware) or "reference" (the published sketch).
    force_fn: true load in newtons at simulated time t (overrides ``load_g``).
    """

    def __init__(
        self,
        *,
        protocol: str = "beadsight",
        clock: SimClock | None = None,
        time_scale: float = 1.0,
        rate_hz: float | None = None,
        noise_g: float = NOISE_G,
        drift_g_per_min: float = 0.0,
        load_g: float = 0.0,
        force_fn: Callable[[float], float] | None = None,
        counts_per_gram: float = REFERENCE_COUNTS_PER_GRAM,
        factor_error: float = 0.0,
        boot_delay_s: float = BOOT_DELAY_S,
        reset_on_open: bool = True,
        seed: int = 0,
        name: str = "virtual scale",
    ):
        if protocol not in ("beadsight", "reference"):
            raise ValueError(
                f"virtual scale protocol must be 'beadsight' or 'reference', got {protocol!r}"
            )
        super().__init__(name, clock if clock is not None else SimClock(time_scale))
        self.protocol = protocol
        self.rate_hz = float(
            rate_hz
            if rate_hz is not None
            else (80.0 if protocol == "beadsight" else REFERENCE_RATE_HZ)
        )
        self.noise_g = float(noise_g)
        self.drift_g_per_min = float(drift_g_per_min)
        self.load_g = float(load_g)
        self.force_fn = force_fn
        self.counts_per_gram = float(counts_per_gram)
        self.factor = self.counts_per_gram * (1.0 + factor_error)
        self.boot_delay_s = float(boot_delay_s)
        self.reset_on_open = bool(reset_on_open)
        self.commands: list[str] = []  # every command line received
        self.sent = 0  # readings sent since boot
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._boot_at: float | None = None
        self._booted = False
        self._power_on = self.clock.now()
        self._next_sample: float = math.inf
        self._tare_counts = 0.0
        self._seq = 0
        self._counter = 0
        self._pending_reply: tuple[float, str] | None = None  # (simulated time, line)
        self._cut_next = False  # the host joined mid-line: send only the next line's tail
        # faults
        self._garbage_to_emit = 0
        self._streaming = True
        self._drop_next = 0
        self._ignore_commands = False

    # --- load ---------------------------------------------------------------------------
    def true_grams(self, t_sim: float) -> float:
        """The load on the cell at simulated time ``t_sim`` (g), without noise or drift."""
        if self.force_fn is not None:
            return float(newtons_to_grams(self.force_fn(t_sim)))
        return self.load_g

    def _counts(self, t_sim: float) -> float:
        drift = self.drift_g_per_min * (t_sim - self._power_on) / 60.0
        noise = self._rng.normal(0.0, self.noise_g) if self.noise_g > 0 else 0.0
        return self.counts_per_gram * (self.true_grams(t_sim) + drift + noise)

    def _mean_counts(self, t_sim: float) -> float:
        return float(np.mean([self._counts(t_sim) for _ in range(TARE_SAMPLES)]))

    # --- faults -------------------------------------------------------------------------
    def emit_garbage(self, lines: int = 3) -> None:
        """Send ``lines`` unreadable lines between readings (line noise, a reset glitch)."""
        with self._lock:
            self._garbage_to_emit += lines

    def stop_streaming(self) -> None:
        """Stop sending readings (a hung Arduino); the port stays open."""
        with self._lock:
            self._streaming = False

    def resume_streaming(self) -> None:
        with self._lock:
            self._streaming = True
            self._next_sample = self.clock.now()

    def drop_next(self, readings: int) -> None:
        """Skip sending the next ``readings`` samples (their seq/counter still advance)."""
        with self._lock:
            self._drop_next += readings

    def ignore_commands(self, ignore: bool = True) -> None:
        """Stop answering commands (e.g. the reference sketch, or a wedged firmware)."""
        with self._lock:
            self._ignore_commands = ignore

    # --- pty hooks ------------------------------------------------------------------------
    def on_host_open(self) -> None:
        with self._lock:
            if not self.reset_on_open:  # already streaming: the host joins mid-line
                if not self._booted:  # powered on a while ago: somewhere in its counter cycle
                    self._boot(self.clock.now(), announce=False)
                    self._seq = int(self._rng.integers(100, 100_000))
                    self._counter = self._seq % 10
                self._cut_next = True
                return
            # opening the port resets the Arduino
            self._booted = False
            self._power_on = self.clock.now()
            self._boot_at = self._power_on + self.boot_delay_s
            self._pending_reply = None
            self._seq = 0
            self._counter = 0
            self.sent = 0

    def on_line(self, line: str) -> None:
        with self._lock:
            self.commands.append(line)
            if not self._booted or self._ignore_commands or self.protocol != "beadsight":
                return  # the reference sketch reads no commands
            if self._pending_reply is not None:
                return  # busy averaging; the real firmware would read it later, we drop it
            self._command(line.strip(), self.clock.now())

    def on_tick(self) -> None:
        with self._lock:
            now = self.clock.now()
            if self._boot_at is not None and now >= self._boot_at:
                self._boot(now)
            if not self._booted:
                return
            if self._pending_reply is not None and now >= self._pending_reply[0]:
                self.write_line(self._pending_reply[1])
                self._pending_reply = None
                self._next_sample = max(self._next_sample, now)
            while self._garbage_to_emit > 0:
                self._garbage_to_emit -= 1
                self.write_raw(self._garbage_line())
            if self._pending_reply is None:
                self._stream(now)

    # --- firmware behaviour -------------------------------------------------------------
    def _boot(self, now: float, announce: bool = True) -> None:
        self._boot_at = None
        self._booted = True
        self._tare_counts = self._mean_counts(now)
        if not announce:
            pass  # the boot line went out before anyone listened
        elif self.protocol == "beadsight":
            self.write_line(format_info(FIRMWARE_VERSION, self.rate_hz, self.factor))
        else:
            self.write_line("start")
        self._next_sample = now + 1.0 / self.rate_hz

    def _stream(self, now: float) -> None:
        burst = 0
        while self._next_sample <= now and burst < MAX_BURST:
            t = self._next_sample
            self._next_sample += 1.0 / self.rate_hz
            burst += 1
            if not self._streaming:
                continue
            grams = (self._counts(t) - self._tare_counts) / self.factor
            line = self._format(t, grams)
            self._seq += 1
            self._counter = (self._counter + 1) % 10
            if self._drop_next > 0:
                self._drop_next -= 1
                continue
            if self._cut_next:
                self._cut_next = False
                line = line[-PARTIAL_CHARS:]
            self.write_line(line)
            self.sent += 1
        if self._next_sample <= now:  # the host stalled for very long: skip ahead
            self._next_sample = now + 1.0 / self.rate_hz

    def _format(self, t_sim: float, grams: float) -> str:
        if self.protocol == "beadsight":
            device_ms = int((t_sim - self._power_on) * 1000.0)
            return format_reading(self._seq, device_ms, grams)
        # the Arduino computes in 32-bit float and prints 2 decimals
        return f"{float(np.float32(encode_reference_value(grams, self._counter))):.2f}"

    def _command(self, line: str, now: float) -> None:
        averaging_s = TARE_SAMPLES / self.rate_hz
        word, _, arg = line.partition(" ")
        if word == "T":
            self._tare_counts = self._mean_counts(now)
            self._pending_reply = (now + averaging_s, "OK T")
        elif word == "C":
            self._calibrate(arg, now, averaging_s)
        elif word == "S":
            try:
                rate = int(float(arg))
            except ValueError:
                rate = -1
            if rate not in SUPPORTED_RATES_HZ:
                self.write_line(
                    f"ERR S rate must be one of {', '.join(map(str, SUPPORTED_RATES_HZ))}"
                )
                return
            self.rate_hz = float(rate)
            self._next_sample = now + 1.0 / self.rate_hz
            self.write_line(f"OK S {rate}")
        elif word == "?":
            self.write_line(format_info(FIRMWARE_VERSION, self.rate_hz, self.factor))
        else:
            self.write_line(f"ERR unknown command '{line}'")

    def _calibrate(self, arg: str, now: float, averaging_s: float) -> None:
        try:
            known = float(arg)
        except ValueError:
            known = math.nan
        if not (math.isfinite(known) and known > 0):
            self.write_line("ERR C needs a positive weight in grams")
            return
        net = self._mean_counts(now) - self._tare_counts
        if abs(net) < MIN_NET_COUNTS:
            self.write_line("ERR C no load on the scale")
            return
        self.factor = net / known
        self._pending_reply = (now + averaging_s, f"OK C {self.factor:.2f}")

    def _garbage_line(self) -> bytes:
        size = int(self._rng.integers(3, 20))
        junk = b"\xfe" + self._rng.integers(0, 256, size=size, dtype=np.uint8).tobytes()
        return junk.replace(b"\n", b"?").replace(b"\r", b"?") + b"\r\n"
