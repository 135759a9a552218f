"""HX711 load-cell scale on an Arduino: background reader with host timestamps.

:class:`HX711Scale` opens the Arduino's serial port, reads one reading per line in a
background thread and stamps each with both host clocks the moment its line arrives.
It speaks the beadsight firmware protocol (``firmware/scale/scale.ino``) and the
reference sketch's plain format, both described in
:mod:`beadsight.data.recording.scale_protocol` (the format force logs keep);
``protocol="auto"`` decides from the first lines (``ProtocolDetector``: one partial
first line cannot make it pick the wrong protocol).

* Readings go to a thread-safe buffer: :meth:`~HX711Scale.latest`,
  :meth:`~HX711Scale.readings_since`, :meth:`~HX711Scale.drain`,
  :meth:`~HX711Scale.wait_for_reading`; optionally ``on_reading`` is called (from the
  reader thread; keep it quick).
* Dropped readings are counted from sequence gaps (``seq`` from the firmware, the rolling
  counter for the reference sketch); unreadable lines are counted and skipped with a
  warning (:attr:`~HX711Scale.garbage_lines`).
* :meth:`~HX711Scale.tare` / :meth:`~HX711Scale.calibrate` run on the firmware for the
  beadsight protocol; for the reference sketch (which takes no commands) they are done
  on the host: ``grams = (device_grams - offset_g) * gain``.
* If the port fails (Arduino unplugged) the reader stops; buffered readings can still be
  read, then every call raises the DeviceNotConnectedError.

Example::

    with HX711Scale("/dev/ttyACM0") as scale:
        scale.tare()
        print(scale.wait_for_reading().grams)
        print(scale.check_drift(30.0), "g/min")
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from beadsight.data.recording.scale_protocol import (
    SUPPORTED_RATES_HZ,
    DeviceInfo,
    ProtocolDetector,
    ReferenceDecoder,
    parse_info,
    parse_reading,
    parse_reference_value,
)
from beadsight.devices.base import (
    DeviceContext,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    ScaleError,
    ScaleReading,
    host_now,
    wait_or_time_out,
)
from beadsight.devices.serial_port import SerialLines, open_serial
from beadsight.geometry import grams_to_newtons

logger = logging.getLogger(__name__)

DEFAULT_BAUDRATE = 57600  # the reference sketch and the beadsight firmware
BOOT_TIMEOUT_S = 5.0  # an Arduino reboots when the port opens; first reading within ~2 s
COMMAND_TIMEOUT_S = 5.0  # tare/calibrate average ~1 s of samples on the firmware
READ_POLL_S = 0.2  # reader thread: longest wait before it re-checks its stop flag
BUFFER_READINGS = 400_000  # ~80 min at 80 Hz; the oldest are dropped beyond this
TARE_SAMPLES = 10  # readings averaged by a host-side tare/calibration
GARBAGE_WARN_FIRST = 5  # warn about the first few unreadable lines ...
GARBAGE_WARN_EVERY = 100  # ... then about every this-many-th
PROTOCOLS = ("auto", "beadsight", "reference")


@dataclass(frozen=True)
class ScaleStats:
    """Counters since connect: readings received, readings lost, unreadable lines."""

    readings: int
    dropped: int
    garbage_lines: int
    protocol: str


class HX711Scale(DeviceContext):
    """An HX711 scale on ``port``; see the module docstring.

    protocol: "auto" (detect), "beadsight" (our firmware) or "reference" (plain grams).
    timeout_s: wait for command replies. boot_timeout_s: wait for the first reading.
    g_to_n: newtons per gram for :attr:`ScaleReading.force_n` (reference: 9.81e-3).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        protocol: str = "auto",
        *,
        timeout_s: float = COMMAND_TIMEOUT_S,
        boot_timeout_s: float = BOOT_TIMEOUT_S,
        buffer_size: int = BUFFER_READINGS,
        on_reading: Callable[[ScaleReading], None] | None = None,
        name: str | None = None,
    ):
        if protocol not in PROTOCOLS:
            raise ValueError(f"scale protocol must be one of {PROTOCOLS}, got {protocol!r}")
        self.port = port
        self.baudrate = int(baudrate)
        self.requested_protocol = protocol
        self.protocol: str | None = None if protocol == "auto" else protocol
        self.timeout_s = float(timeout_s)
        self.boot_timeout_s = float(boot_timeout_s)
        self.on_reading = on_reading
        self.name = name or f"scale {port}"
        self.info: DeviceInfo | None = None
        self.offset_g = 0.0  # host-side tare (reference protocol)
        self.gain = 1.0  # host-side calibration multiplier (reference protocol)
        self.dropped = 0
        self.garbage_lines = 0
        self.received = 0
        self._buffer: deque[ScaleReading] = deque(maxlen=int(buffer_size))
        self._raw: deque[float] = deque(maxlen=TARE_SAMPLES * 10)  # device grams, newest last
        self._cond = threading.Condition()
        self._replies: queue.Queue[str] = queue.Queue()
        self._command_lock = threading.Lock()
        self._decoder = ReferenceDecoder()
        self._last_seq: int | None = None
        self._ref_seq = -1
        self._detector = ProtocolDetector()
        self._latest: ScaleReading | None = None
        self._io: SerialLines | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: DeviceError | None = None

    # --- lifecycle --------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, start the reader and wait for the first reading."""
        if self._io is not None:
            return
        opened_mono = time.monotonic()
        self._io = SerialLines(open_serial(self.port, self.baudrate, device=self.name), self.name)
        self._stop.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name=f"{self.name} reader", daemon=True)
        self._thread.start()
        try:
            self.wait_for_reading(self.boot_timeout_s, after_mono=opened_mono)
        except DeviceTimeoutError:
            garbage = self.garbage_lines
            self.close()
            raise DeviceTimeoutError(
                self.name,
                f"no readings within {self.boot_timeout_s:g} s of opening {self.port}"
                + (f" ({garbage} unreadable lines)" if garbage else ""),
                f"is the scale sketch flashed and the baud rate {self.baudrate}? "
                "Check the HX711 wiring (docs/hardware.md)",
            ) from None
        except BaseException:
            self.close()
            raise
        logger.info(
            "%s connected (%s protocol%s)",
            self.name,
            self.protocol,
            f", {self.info}" if self.info else "",
        )

    def close(self) -> None:
        """Stop the reader and close the port; buffered readings stay readable."""
        self._stop.set()
        thread, self._thread = self._thread, None
        io, self._io = self._io, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        if io is not None:
            io.close()

    @property
    def stats(self) -> ScaleStats:
        return ScaleStats(
            self.received, self.dropped, self.garbage_lines, self.protocol or "unknown"
        )

    # --- readings ---------------------------------------------------------------------
    def latest(self) -> ScaleReading | None:
        """The newest reading (None before the first); raises if the scale was lost and
        nothing was ever read."""
        with self._cond:
            if self._latest is None and self._error is not None:
                raise self._error
            return self._latest

    def wait_for_reading(
        self, timeout_s: float | None = None, *, after_mono: float | None = None
    ) -> ScaleReading:
        """The newest reading that arrived after ``after_mono`` (default: any), waiting up to
        ``timeout_s`` (default: the command timeout). Raises DeviceTimeoutError when the
        scale stopped streaming, DeviceNotConnectedError when it was lost."""
        timeout = self.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                latest = self._latest
                if latest is not None and (after_mono is None or latest.t_mono > after_mono):
                    return latest
                self._wait_news(
                    deadline,
                    f"no reading for {timeout:g} s; the scale stopped streaming",
                    "check the USB cable; reset the Arduino",
                )

    def readings_since(self, t_mono: float) -> list[ScaleReading]:
        """Buffered readings with ``t_mono`` strictly after ``t_mono`` (oldest first); the
        buffer is left as is."""
        with self._cond:
            out = [r for r in reversed(self._buffer) if r.t_mono > t_mono]
            if not out and not self._buffer and self._error is not None:
                raise self._error
        out.reverse()
        return out

    def drain(self) -> list[ScaleReading]:
        """Every buffered reading (oldest first), emptying the buffer. Raises the
        connection error once the scale is lost and the buffer is empty."""
        with self._cond:
            out = list(self._buffer)
            self._buffer.clear()
            if not out and self._error is not None:
                raise self._error
        return out

    def check_drift(self, duration_s: float) -> float:
        """Record ``duration_s`` with no load and return the fitted drift in grams/minute."""
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        start = time.monotonic()
        time.sleep(duration_s)
        readings = self.readings_since(start)
        if len(readings) < 3:
            raise DeviceTimeoutError(
                self.name, f"only {len(readings)} readings in {duration_s:g} s; cannot fit a drift"
            )
        t = np.array([r.t_mono for r in readings]) - start
        grams = np.array([r.grams for r in readings])
        slope_g_per_s = np.polyfit(t, grams, 1)[0]
        return float(slope_g_per_s * 60.0)

    def measured_rate_hz(self, window_s: float = 5.0) -> float:
        """Readings per second over the last ``window_s`` of the buffer (NaN if < 2)."""
        with self._cond:
            if not self._buffer:
                return math.nan
            newest = self._buffer[-1].t_mono
            times = [r.t_mono for r in self._buffer if r.t_mono >= newest - window_s]
        if len(times) < 2 or times[-1] <= times[0]:
            return math.nan
        return (len(times) - 1) / (times[-1] - times[0])

    # --- commands ---------------------------------------------------------------------
    def tare(self, samples: int = TARE_SAMPLES) -> None:
        """Make the current load read 0 g (firmware ``T``; host-side for the reference)."""
        if self._uses_firmware():
            self._command("T", "OK T")
            return
        self.offset_g = float(np.mean(self._fresh_raw(samples)))
        logger.info("%s: host tare offset %.2f g", self.name, self.offset_g)

    def calibrate(self, known_grams: float, samples: int = TARE_SAMPLES) -> float:
        """Calibrate with ``known_grams`` on the (tared) scale.

        Returns the new calibration: the firmware's ADC counts per gram (beadsight
        protocol, stored in its EEPROM) or the host-side gain (reference protocol).
        """
        if not (math.isfinite(known_grams) and known_grams > 0):
            raise ValueError(f"known_grams must be a positive weight in grams, got {known_grams}")
        if self._uses_firmware():
            reply = self._command(f"C {known_grams:.2f}", "OK C")
            try:
                return float(reply.split()[2])
            except (IndexError, ValueError):
                raise ScaleError(self.name, f"unreadable calibration reply {reply!r}") from None
        measured = float(np.mean(self._fresh_raw(samples))) - self.offset_g
        if measured <= 0:
            raise ScaleError(
                self.name,
                f"calibration weight reads {measured:.2f} g after tare",
                "tare empty, then put the weight on",
            )
        self.gain = known_grams / measured
        logger.info("%s: host calibration gain %.5f", self.name, self.gain)
        return self.gain

    def set_rate(self, rate_hz: int) -> None:
        """Firmware ``S <hz>``: the HX711's output rate, 10 or 80 (needs RATE wired)."""
        if rate_hz not in SUPPORTED_RATES_HZ:
            raise ValueError(f"rate_hz must be one of {SUPPORTED_RATES_HZ}, got {rate_hz}")
        self._require_firmware("set_rate")
        self._command(f"S {rate_hz}", "OK S")

    def query_info(self) -> DeviceInfo:
        """Firmware ``?``: name, version, rate and calibration factor."""
        self._require_firmware("query_info")
        return parse_info(self._command("?", "I,"))

    def _uses_firmware(self) -> bool:
        if self.protocol is None:
            self.wait_for_reading()
        return self.protocol == "beadsight"

    def _require_firmware(self, what: str) -> None:
        if not self._uses_firmware():
            raise ScaleError(
                self.name, f"{what} needs the beadsight firmware; this scale speaks {self.protocol}"
            )

    def _command(self, text: str, expect: str) -> str:
        io = self._io
        if io is None:
            raise self._error or DeviceNotConnectedError(
                self.name, "not connected", "call connect() first"
            )
        with self._command_lock:
            while not self._replies.empty():
                self._replies.get_nowait()
            io.write_line(text)
            deadline = time.monotonic() + self.timeout_s
            while True:
                try:
                    reply = self._replies.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    if self._error is not None:
                        raise self._error from None
                    raise DeviceTimeoutError(
                        self.name,
                        f"no reply to {text!r} within {self.timeout_s:g} s",
                        "is the beadsight firmware flashed?",
                    ) from None
                if reply.startswith("ERR"):
                    raise ScaleError(self.name, f"{text!r} refused: {reply}")
                if reply.startswith(expect):
                    return reply
                logger.debug("%s: ignoring reply %r while waiting for %r", self.name, reply, expect)

    def _wait_news(self, deadline: float, message: str, hint: str | None = None) -> None:
        """Wait (``self._cond`` held) for the reader's next reading; raise the error that
        stopped the reader, or DeviceTimeoutError(``message``, ``hint``) after ``deadline``."""
        if self._error is not None:
            raise self._error
        wait_or_time_out(self._cond, deadline, self.name, message, hint)

    def _fresh_raw(self, samples: int) -> list[float]:
        """The next ``samples`` device readings (grams before host tare/gain)."""
        deadline = time.monotonic() + self.timeout_s + samples
        with self._cond:
            start = self.received
            while self.received - start < samples:
                self._wait_news(
                    deadline, f"fewer than {samples} readings arrived for tare/calibration"
                )
            return list(self._raw)[-samples:]

    # --- reader thread ------------------------------------------------------------------
    def _run(self) -> None:
        io = self._io
        assert io is not None
        while not self._stop.is_set():
            try:
                line = io.read_line(time.monotonic() + READ_POLL_S)
            except DeviceError as e:
                if not self._stop.is_set():
                    logger.error("%s", e)
                    with self._cond:
                        self._error = e
                        self._cond.notify_all()
                return
            if line is None or not line:
                continue
            t_unix, t_mono = host_now()
            try:
                self._handle(line, t_unix, t_mono)
            except ValueError:
                self._garbage(line)

    def _handle(self, line: str, t_unix: float, t_mono: float) -> None:
        if self.protocol is None:
            self._detect(line, t_unix, t_mono)
            return
        if self.protocol == "beadsight":
            self._handle_beadsight(line, t_unix, t_mono)
        else:
            self._handle_reference(line, t_unix, t_mono)

    def _detect(self, line: str, t_unix: float, t_mono: float) -> None:
        """Feed the protocol detector; ValueError for garbage."""
        protocol, lines = self._detector.feed(line, (line, t_unix, t_mono))
        if protocol is None:
            return
        self.protocol = protocol
        dropped = (
            f"; dropped {self._detector.dropped!r} (maybe partial)"
            if self._detector.dropped
            else ""
        )
        logger.info("%s: detected the %s protocol%s", self.name, protocol, dropped)
        for args in lines:
            self._handle(*args)

    def _handle_beadsight(self, line: str, t_unix: float, t_mono: float) -> None:
        if line.startswith("R,"):
            sample = parse_reading(line)
            if self._last_seq is not None and sample.seq > self._last_seq + 1:
                self._lost(sample.seq - self._last_seq - 1)
            self._last_seq = sample.seq
            self._add(sample.grams, sample.seq, sample.device_ms, t_unix, t_mono)
        elif line.startswith("I,"):
            self.info = parse_info(line)
            if not self._command_lock.locked() and self.received:  # a boot line, not a '?' reply
                logger.warning("%s: the scale restarted (and tared itself) mid-session", self.name)
                self._last_seq = None  # the sequence restarts at 0
            self._replies.put(line)
        elif line.startswith(("OK", "ERR")):
            self._replies.put(line)
        elif line.startswith("#"):
            logger.debug("%s: %s", self.name, line)
        else:
            raise ValueError(line)

    def _handle_reference(self, line: str, t_unix: float, t_mono: float) -> None:
        if line.strip().lower() == "start":
            self._decoder.reset()
            logger.info("%s: the reference sketch (re)started and tared", self.name)
            return
        grams, _, lost = self._decoder.decode(parse_reference_value(line))
        if lost:
            self._lost(lost)
        self._ref_seq += 1 + lost
        self._add(grams, self._ref_seq, None, t_unix, t_mono)

    def _add(
        self, device_grams: float, seq: int, device_ms: int | None, t_unix: float, t_mono: float
    ) -> None:
        grams = round((device_grams - self.offset_g) * self.gain, 2)
        reading = ScaleReading(
            t_unix, t_mono, grams, float(grams_to_newtons(grams)), seq, device_ms
        )
        with self._cond:
            self._buffer.append(reading)
            self._raw.append(device_grams)
            self._latest = reading
            self.received += 1
            self._cond.notify_all()
        if self.on_reading is not None:
            try:
                self.on_reading(reading)
            except Exception:  # noqa: BLE001 - a failing callback must not stop the reader
                logger.exception("%s: on_reading callback failed", self.name)

    def _lost(self, count: int) -> None:
        self.dropped += count
        logger.warning(
            "%s: %d reading(s) lost (sequence gap); %d so far", self.name, count, self.dropped
        )

    def _garbage(self, line: str) -> None:
        self.garbage_lines += 1
        n = self.garbage_lines
        if n <= GARBAGE_WARN_FIRST or n % GARBAGE_WARN_EVERY == 0:
            logger.warning("%s: skipped unreadable line %r (%d so far)", self.name, line[:40], n)
