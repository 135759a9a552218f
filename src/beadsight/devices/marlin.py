"""Marlin-style G-code printer driver: the stage that presses the finger onto the sensor.

Protocol (what :class:`MarlinPrinter` does on the wire):

* **Connect**: open the port (exclusively), wait up to ``banner_timeout_s`` for the boot
  banner (a ``start`` line or a line naming Marlin; most boards reset when the port
  opens), let the boot chatter settle, then ``M110 N0`` (reset line numbers) and ``G90``
  (absolute positioning). Boards that do not reset send no banner: the wait times out
  quietly and the ``M110`` handshake proves the printer is there.
* **Every command** is framed ``N<n> <gcode>*<checksum>`` (checksum = XOR of all bytes
  before ``*``) and sent one at a time: the next goes only after the printer's ``ok``.
  ``Resend: <n>`` (after a transmission error such as ``Error:checksum mismatch``)
  resends the requested lines after the ``ok`` that follows it; ``echo:busy:
  processing`` keep-alives extend the deadline; ``echo:`` lines are logged; other
  ``Error:`` lines raise :class:`PrinterError` with the printer's text; no ``ok`` in time
  raises :class:`DeviceTimeoutError` naming the port and the command.
* **Safety**: :meth:`move` checks the whole straight path against the
  :class:`~beadsight.devices.envelope.SafetyEnvelope` and raises
  :class:`SafetyError` *before anything is sent*; moves are refused until :meth:`home`
  has run. :meth:`send` refuses motion and positioning commands (use :meth:`move`).
* **Log**: every acknowledged command becomes a :class:`CommandRecord` ``(t_unix,
  t_mono, gcode, x_mm, y_mm, z_mm)`` in :attr:`MarlinPrinter.command_log` and is passed
  to ``on_command``.

Example::

    with MarlinPrinter("/dev/ttyUSB0", envelope=SafetyEnvelope()) as printer:
        printer.home()
        printer.heaters_off()
        printer.move(151.8, 108.9, 137.5, feed_mm_min=700)
        printer.move(None, None, 127.5, feed_mm_min=200)
        printer.wait_for_motion()
        printer.dwell(1000)
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from beadsight.devices.base import (
    CommandRecord,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    PrinterError,
    SafetyError,
    host_now,
)
from beadsight.devices.envelope import SafetyEnvelope
from beadsight.devices.serial_port import SerialLines, open_serial

logger = logging.getLogger(__name__)

DEFAULT_BAUDRATE = 115200  # Marlin's usual USB serial rate
DEFAULT_TIMEOUT_S = 10.0  # max wait for an 'ok' beyond the expected motion/dwell time
BANNER_TIMEOUT_S = 5.0  # boards that reset on connect print 'start' within ~2 s
BOOT_SETTLE_S = 0.3  # after the banner, boot chatter is over once the line is quiet this long
BOOT_CHATTER_MAX_S = 5.0  # ... or after this long, whatever it prints
HOME_TIMEOUT_S = 180.0  # G28 on a large printer at slow homing feed
MAX_RESENDS = 5  # resend requests tolerated per command before giving up
RESEND_HISTORY = 64  # sent lines kept for 'Resend:' requests
MAX_GCODE_CHARS = 80  # Marlin's MAX_CMD_SIZE is 96 including N<n> and *<checksum>
MAX_GARBAGE_WARNINGS = 5  # warn about this many garbage lines, then count silently
COORD_DECIMALS = 3  # mm resolution of generated G-code coordinates

TRANSMISSION_ERRORS = (
    "checksum mismatch",
    "line number is not last line number+1",
    "no checksum with line number",
    "no line number with checksum",
    "format error",
)  # Marlin 'Error:' texts that precede a 'Resend:' and are recovered from
RESERVED_COMMANDS = {
    "G0": "use move()",
    "G1": "use move()",
    "G2": "use move()",
    "G3": "use move()",
    "G5": "use move()",
    "G28": "use home()",
    "G29": "bed levelling moves the head outside the envelope",
    "G90": "the driver keeps absolute positioning",
    "G91": "the driver keeps absolute positioning",
    "G92": "changing the coordinate origin defeats the envelope",
    "M110": "the driver manages line numbers",
    "M112": "use emergency_stop()",
}  # send() refuses these: they move the head or break the driver's bookkeeping
_POSITION_RE = re.compile(r"X:\s*(-?[\d.]+)\s+Y:\s*(-?[\d.]+)\s+Z:\s*(-?[\d.]+)")
_NAN3 = (math.nan, math.nan, math.nan)


def checksum(text: str) -> int:
    """Marlin's line checksum: XOR of every byte of ``text`` (0..255)."""
    value = 0
    for byte in text.encode("ascii"):
        value ^= byte
    return value


def frame_line(line_number: int, gcode: str) -> str:
    """``N<n> <gcode>*<checksum>``, the form Marlin checks for lost or corrupted lines."""
    body = f"N{line_number} {gcode}"
    return f"{body}*{checksum(body)}"


def clean_gcode(gcode: str) -> str:
    """Strip comments and whitespace; raise ValueError for text Marlin cannot take."""
    text = gcode.split(";", 1)[0].strip()
    if not text:
        raise ValueError(f"empty G-code command {gcode!r}")
    if not text.isascii() or not text.isprintable() or "*" in text:
        raise ValueError(f"G-code {gcode!r} must be printable ASCII without '*' or newlines")
    if len(text) > MAX_GCODE_CHARS:
        raise ValueError(f"G-code {gcode!r} is longer than {MAX_GCODE_CHARS} characters")
    return text


def parse_position(lines: list[str]) -> tuple[float, float, float] | None:
    """(x, y, z) mm from an ``M114`` report (``X:1.00 Y:2.00 Z:3.00 E:0.00 Count ...``)."""
    for line in lines:
        match = _POSITION_RE.search(line.split("Count", 1)[0])
        if match:
            return tuple(float(v) for v in match.groups())  # type: ignore[return-value]
    return None


def _fmt(value: float) -> str:
    text = f"{value:.{COORD_DECIMALS}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


class MarlinPrinter:
    """A Marlin printer on a serial port; see the module docstring for the protocol.

    port: serial device (``/dev/ttyUSB0``, ``COM3``, a virtual printer's ``/dev/pts/N``).
    envelope: where the finger may go (printer coordinates, mm).
    timeout_s: how long to wait for an ``ok`` beyond the motion/dwell the command waits for.
    banner_timeout_s: how long :meth:`connect` waits for the boot banner (0: do not wait).
    boot_settle_s: after the banner, boot chatter is over once the line is quiet this long.
    home_timeout_s: how long ``G28`` may take.
    on_command: called with each :class:`CommandRecord` as it is acknowledged.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        envelope: SafetyEnvelope | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        *,
        banner_timeout_s: float = BANNER_TIMEOUT_S,
        home_timeout_s: float = HOME_TIMEOUT_S,
        boot_settle_s: float = BOOT_SETTLE_S,
        on_command: Callable[[CommandRecord], None] | None = None,
        name: str | None = None,
    ):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.port = port
        self.baudrate = int(baudrate)
        self.envelope = envelope if envelope is not None else SafetyEnvelope()
        self.timeout_s = float(timeout_s)
        self.banner_timeout_s = float(banner_timeout_s)
        self.home_timeout_s = float(home_timeout_s)
        self.boot_settle_s = float(boot_settle_s)
        self.on_command = on_command
        self.name = name or f"printer {port}"
        self.command_log: list[CommandRecord] = []
        self.banner_seen = False
        self.resend_count = 0  # lines resent on the printer's request (transmission errors)
        self.garbage_lines = 0  # unreadable lines received and skipped
        self._io: SerialLines | None = None
        self._lock = threading.RLock()
        self._next_line = 0
        self._history: OrderedDict[int, str] = OrderedDict()
        # the commanded position; None until homed (after every connect)
        self._target: tuple[float, float, float] | None = None
        self._motion_end_mono = 0.0  # host estimate of when queued motion finishes
        self._halted: str | None = None

    # --- lifecycle --------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, wait for the banner, reset line numbers and set absolute mode."""
        if self._io is not None:
            return
        self._io = SerialLines(open_serial(self.port, self.baudrate, device=self.name), self.name)
        self._halted = None
        self._target = None  # a board that reset has lost its position: home again
        try:
            self.banner_seen = self._wait_for_banner()
            self._next_line = 0
            self._history.clear()
            self._transact("M110 N0", self.timeout_s, line_number=0)
            self._next_line = 1
            self._transact("G90", self.timeout_s)
        except BaseException:
            self.close()
            raise
        logger.info(
            "%s connected (banner %s)", self.name, "seen" if self.banner_seen else "not sent"
        )

    def close(self) -> None:
        """Close the port (motors and heaters keep their state). Safe to call twice."""
        io, self._io = self._io, None
        if io is not None:
            io.close()

    def __enter__(self) -> MarlinPrinter:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._io is not None

    @property
    def halted(self) -> bool:
        """True after :meth:`emergency_stop` or a fatal printer error."""
        return self._halted is not None

    @property
    def target(self) -> tuple[float, float, float] | None:
        """The last commanded position (x, y, z) mm, or None before homing."""
        return self._target

    # --- motion -----------------------------------------------------------------------
    def home(self) -> tuple[float, float, float]:
        """``G28`` (home all axes), then read and return the position (x, y, z) mm.

        G28 is not checked against the envelope: make sure homing cannot hit the sensor.
        """
        self._transact("G28", self.home_timeout_s)
        position = self._read_position()
        self._target = position
        self._motion_end_mono = time.monotonic()
        return position

    def move(self, x: float | None, y: float | None, z: float | None, feed_mm_min: float) -> None:
        """Straight move (``G1``, absolute) to x, y, z mm at ``feed_mm_min``; None keeps an axis.

        Returns once the printer has *planned* the move; call :meth:`wait_for_motion` to
        wait for the finger to get there. Raises SafetyError (nothing sent) when the path
        leaves the envelope or the printer has not been homed. If homing leaves the head
        low (below the envelope's clear height, outside its box), the only move allowed
        from there is straight up: ``move(None, None, z_clear, feed)``.
        """
        start = self._target
        if start is None:
            raise SafetyError(self.name, "refused move: position unknown; call home() first")
        target = tuple(float(s if v is None else v) for v, s in zip((x, y, z), start, strict=True))
        self.envelope.check_move(start, target, float(feed_mm_min), device=self.name)  # type: ignore[arg-type]
        words = [
            f"{axis}{_fmt(v)}" for axis, v, s in zip("XYZ", target, start, strict=True) if v != s
        ]
        gcode = " ".join(["G1", *words, f"F{_fmt(float(feed_mm_min))}"])
        duration_s = math.dist(start, target) / float(feed_mm_min) * 60.0
        with self._lock:
            self._transact(gcode, self.timeout_s + self._motion_remaining_s(), new_target=target)  # type: ignore[arg-type]
            self._motion_end_mono = max(self._motion_end_mono, time.monotonic()) + duration_s

    def wait_for_motion(self) -> None:
        """``M400``: return once every queued move has finished."""
        self._transact("M400", self.timeout_s + self._motion_remaining_s())
        self._motion_end_mono = time.monotonic()

    def dwell(self, ms: float) -> None:
        """``G4 P<ms>``: the printer finishes queued moves, then pauses ``ms`` milliseconds."""
        if not (math.isfinite(ms) and ms >= 0):
            raise ValueError(f"dwell ms must be a finite number >= 0, got {ms}")
        self._transact(
            f"G4 P{int(round(ms))}", self.timeout_s + self._motion_remaining_s() + ms / 1000.0
        )
        self._motion_end_mono = time.monotonic()

    def position(self) -> tuple[float, float, float]:
        """``M114``: the position (x, y, z) mm the printer reports.

        Real Marlin reports the position of the last *planned* move; call
        :meth:`wait_for_motion` first to be sure the head is there. The virtual printer
        reports the current interpolated position.
        """
        return self._read_position()

    def heaters_off(self, extruders: int = 1) -> None:
        """``M104 S0`` for each extruder and ``M140 S0`` (bed): the rig never heats."""
        if extruders < 1:
            raise ValueError(f"extruders must be >= 1, got {extruders}")
        if extruders == 1:
            self._transact("M104 S0", self.timeout_s)
        else:
            for tool in range(extruders):
                self._transact(f"M104 T{tool} S0", self.timeout_s)
        self._transact("M140 S0", self.timeout_s)

    def emergency_stop(self) -> None:
        """Send ``M112`` at once (no line number, no waiting for the command lock).

        Marlin halts immediately and needs a reset; every later command raises
        PrinterError. Safe to call from another thread while a command is waiting.
        """
        io = self._io
        if io is None:
            raise DeviceNotConnectedError(self.name, "cannot send M112: not connected")
        io.write_line("M112")
        self._halted = "emergency stop (M112) sent"
        self._record("M112", self._target)
        logger.warning("%s: emergency stop (M112) sent", self.name)

    def send(self, gcode: str, timeout_s: float | None = None) -> list[str]:
        """Send one non-motion command (e.g. ``M105``) and return the lines before its ``ok``.

        Motion, homing and positioning commands are refused (SafetyError): use
        :meth:`move`, :meth:`home`, :meth:`emergency_stop`.
        """
        text = clean_gcode(gcode)
        word = text.split()[0].upper()
        if word in RESERVED_COMMANDS:
            raise SafetyError(self.name, f"send({text!r}) refused: {RESERVED_COMMANDS[word]}")
        return self._transact(text, self.timeout_s if timeout_s is None else float(timeout_s))

    # --- protocol ---------------------------------------------------------------------
    def _motion_remaining_s(self) -> float:
        return max(0.0, self._motion_end_mono - time.monotonic())

    def _read_position(self) -> tuple[float, float, float]:
        lines = self._transact("M114", self.timeout_s + self._motion_remaining_s())
        position = parse_position(lines)
        if position is None:
            raise PrinterError(
                self.name, f"could not read the position from the M114 reply {lines!r}"
            )
        return position

    def _require_io(self) -> SerialLines:
        if self._io is None:
            raise DeviceNotConnectedError(
                self.name, "not connected", "call connect() or use 'with MarlinPrinter(...)'"
            )
        if self._halted is not None:
            raise PrinterError(
                self.name,
                f"printer is halted ({self._halted})",
                "reset or power-cycle it, then reconnect",
            )
        return self._io

    def _transact(
        self,
        gcode: str,
        timeout_s: float,
        *,
        line_number: int | None = None,
        new_target: tuple[float, float, float] | None = None,
    ) -> list[str]:
        """Send one framed command and wait for its ``ok``; returns the lines before it."""
        with self._lock:
            io = self._require_io()
            self._drain_unsolicited(io)
            n = self._next_line if line_number is None else line_number
            framed = frame_line(n, gcode)
            self._history[n] = framed
            while len(self._history) > RESEND_HISTORY:
                self._history.popitem(last=False)
            io.write_line(framed)
            if line_number is None:
                self._next_line = n + 1
            replies = self._await_ok(io, gcode, n, timeout_s)
            if new_target is not None:
                self._target = new_target
            self._record(gcode, self._target)
            return replies

    def _await_ok(self, io: SerialLines, gcode: str, n: int, timeout_s: float) -> list[str]:
        deadline = time.monotonic() + timeout_s
        replies: list[str] = []
        resend_from: int | None = None
        extra_oks = 0  # acks owed to earlier lines that were resent before ours
        resends = 0
        last_error = ""
        while True:
            line = io.read_line(deadline)
            if line is None:
                raise self._timeout(gcode, timeout_s, last_error)
            low = line.lower()
            if low.startswith("ok"):
                if resend_from is not None:
                    resends += 1
                    if resends > MAX_RESENDS:
                        raise PrinterError(
                            self.name,
                            f"{gcode!r} was rejected {MAX_RESENDS} times (last error: {last_error})",
                            "check the USB cable and that the baud rate matches the printer",
                        )
                    extra_oks = self._resend(io, resend_from, n)
                    resend_from = None
                elif extra_oks:
                    extra_oks -= 1
                else:
                    rest = line[2:].strip()
                    if rest and not rest.startswith(("N", "P")):  # 'ok T:..' carries data
                        replies.append(rest)
                    return replies
            elif low.startswith(("resend:", "rs ")):
                resend_from = self._parse_resend(line, gcode)
            elif low.startswith(("error:", "!!")):
                text = line.split(":", 1)[1].strip() if ":" in line else line
                if any(marker in text.lower() for marker in TRANSMISSION_ERRORS):
                    last_error = text
                    logger.warning("%s: transmission error on %r: %s", self.name, gcode, text)
                else:
                    self._fatal_error(gcode, text)
            elif "busy:" in low:
                deadline = max(deadline, time.monotonic() + self.timeout_s)
            elif low.startswith("echo:"):
                self._echo(line, gcode)
            elif low == "start":
                self._reset_detected(f"while waiting for {gcode!r}")
            elif self._is_garbage(line):
                self._garbage(line, gcode)
            else:
                replies.append(line)
            if time.monotonic() > deadline:  # a device that chatters but never says ok
                raise self._timeout(gcode, timeout_s, last_error)

    def _resend(self, io: SerialLines, first: int, current: int) -> int:
        """Resend lines ``first..current``; returns how many extra ``ok``s that owes."""
        if first > current or first not in self._history:
            raise PrinterError(
                self.name,
                f"printer asked to resend line {first}, which was not sent or is too old (current line {current})",
                "reconnect to resynchronise line numbers",
            )
        for number in range(first, current + 1):
            io.write_line(self._history[number])
            self.resend_count += 1
        logger.info("%s: resent lines %d..%d", self.name, first, current)
        return current - first

    def _parse_resend(self, line: str, gcode: str) -> int:
        digits = re.findall(r"\d+", line)
        if not digits:
            raise PrinterError(self.name, f"unreadable resend request {line!r} after {gcode!r}")
        return int(digits[0])

    def _fatal_error(self, gcode: str, text: str) -> None:
        if "halted" in text.lower() or "kill" in text.lower():
            self._halted = f"printer says 'Error:{text}'"
        raise PrinterError(self.name, f"{gcode!r} failed: printer says 'Error:{text}'")

    def _echo(self, line: str, gcode: str) -> None:
        if "unknown command" in line.lower():
            logger.warning("%s: %s (sent %r)", self.name, line, gcode)
        else:
            logger.debug("%s: %s", self.name, line)

    def _reset_detected(self, when: str) -> None:
        self._target = None
        self._next_line = 0
        raise PrinterError(
            self.name,
            f"printer restarted ('start') {when}; its position is lost",
            "check the power supply and USB cable, then reconnect and home again",
        )

    @staticmethod
    def _is_garbage(line: str) -> bool:
        return "\ufffd" in line or not line.isprintable()

    def _garbage(self, line: str, gcode: str) -> None:
        self.garbage_lines += 1
        if self.garbage_lines <= MAX_GARBAGE_WARNINGS:
            logger.warning(
                "%s: skipped unreadable line %r (waiting for %r)", self.name, line[:40], gcode
            )

    def _timeout(self, gcode: str, timeout_s: float, last_error: str) -> DeviceTimeoutError:
        extra = f"; last printer error: {last_error}" if last_error else ""
        return DeviceTimeoutError(
            self.name,
            f"no 'ok' for {gcode!r} within {timeout_s:.1f} s{extra}",
            f"is the printer on and is {self.baudrate} its baud rate? "
            f"Close other programs using {self.port} (OctoPrint, Pronterface)",
        )

    def _drain_unsolicited(self, io: SerialLines) -> None:
        """Handle lines that arrived between commands (keep-alives, resets, errors)."""
        while (line := io.read_line(0.0)) is not None:
            low = line.lower()
            if low == "start":
                self._reset_detected("between commands")
            elif low.startswith(("error:", "!!")):
                self._fatal_error("(between commands)", line.split(":", 1)[-1].strip())
            elif self._is_garbage(line):
                self._garbage(line, "(nothing)")
            else:
                logger.debug("%s: %s", self.name, line)

    def _wait_for_banner(self) -> bool:
        if self.banner_timeout_s <= 0:
            return False
        io = self._io
        assert io is not None
        deadline = time.monotonic() + self.banner_timeout_s
        while True:
            line = io.read_line(deadline)
            if line is None:
                logger.info(
                    "%s: no start banner within %.1f s; assuming a board that does not reset on connect",
                    self.name,
                    self.banner_timeout_s,
                )
                return False
            if line.lower() == "start" or "marlin" in line.lower():
                break
        hard_stop = time.monotonic() + BOOT_CHATTER_MAX_S
        while (
            line := io.read_line(min(time.monotonic() + self.boot_settle_s, hard_stop))
        ) is not None:
            logger.debug("%s boot: %s", self.name, line)
            if time.monotonic() > hard_stop:
                break
        return True

    def _record(self, gcode: str, target: tuple[float, float, float] | None) -> None:
        t_unix, t_mono = host_now()
        record = CommandRecord(t_unix, t_mono, gcode, *(target if target is not None else _NAN3))
        self.command_log.append(record)
        if self.on_command is not None:
            self.on_command(record)
