"""Marlin-style G-code printer driver: the stage that presses the finger onto the sensor.

The wire protocol (line numbers, checksums, resends, re-synchronisation, keep-alives,
``ok`` accounting) lives in :mod:`beadsight.devices.marlin_link`; this module holds the
printer operations on top of it:

* **Connect**: open the port (exclusively), wait up to ``banner_timeout_s`` for the boot
  banner (a ``start`` line or a line naming Marlin; most boards reset when the port
  opens), let the boot chatter settle, then ``M110 N0`` (reset line numbers) and ``G90``
  (absolute positioning). Boards that do not reset send no banner: the wait times out
  quietly and the ``M110`` handshake proves the printer is there.
* **Waits end only when the printer is done**: :meth:`~MarlinPrinter.wait_for_motion`
  (``M400``), :meth:`~MarlinPrinter.dwell` (``G4``) and :meth:`~MarlinPrinter.home`
  (``G28``) are followed by ``M114``, whose reply carries the position and comes only
  after the wait, so a duplicated ``ok`` cannot end a wait early. After ``M400``/``G4``
  the reported position must be the commanded one (within ``POSITION_TOLERANCE_MM``).
  Keep-alives extend a wait only up to an overall deadline (``busy_timeout_s`` beyond the
  expected time; ``home_timeout_s`` for homing).
* **Safety**: :meth:`~MarlinPrinter.move` checks the whole straight path against the
  :class:`~beadsight.devices.envelope.SafetyEnvelope` and raises :class:`SafetyError`
  *before anything is sent*; moves are refused until :meth:`~MarlinPrinter.home` has run;
  from a position outside the envelope (e.g. homed at Z=0) only a straight rise is
  allowed. :meth:`~MarlinPrinter.send` refuses motion and positioning commands.
* **Desync**: when printer and driver disagree about which commands ran (a resend
  request for an acknowledged line, a position other than commanded), nothing is
  replayed: the driver re-synchronises line numbers, raises the finger straight up to the
  clear height, re-reads the position and raises :class:`PrinterDesyncError`.
* **Log**: every acknowledged command becomes a :class:`CommandRecord` ``(t_unix,
  t_mono, gcode, x_mm, y_mm, z_mm)`` in :attr:`MarlinPrinter.command_log` and is passed
  to ``on_command``.

Example::

    with MarlinPrinter("/dev/ttyUSB0", envelope=SafetyEnvelope()) as printer:
        printer.home()
        printer.heaters_off()
        printer.move(None, None, 137.5, feed_mm_min=700)   # straight up first
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
from collections.abc import Callable
from typing import NoReturn

from beadsight.devices.base import (
    CommandRecord,
    DeviceContext,
    DeviceError,
    DeviceNotConnectedError,
    PrinterDesyncError,
    PrinterError,
    SafetyError,
    host_now,
)
from beadsight.devices.envelope import SafetyEnvelope
from beadsight.devices.marlin_link import (
    MarlinLink,
    checksum,
    clean_gcode,
    frame_line,
    has_position,
)
from beadsight.devices.serial_port import SerialLines, open_serial

__all__ = ["MarlinPrinter", "checksum", "clean_gcode", "frame_line", "parse_position"]

logger = logging.getLogger(__name__)

DEFAULT_BAUDRATE = 115200  # Marlin's usual USB serial rate
DEFAULT_TIMEOUT_S = 10.0  # max wait for an 'ok' beyond the expected motion/dwell time
BANNER_TIMEOUT_S = 5.0  # boards that reset on connect print 'start' within ~2 s
BOOT_SETTLE_S = 0.3  # after the banner, boot chatter is over once the line is quiet this long
HOME_TIMEOUT_S = 180.0  # G28 on a large printer at slow homing feed, keep-alives included
BUSY_TIMEOUT_S = 60.0  # keep-alives may stretch a command this far beyond its expected time
COORD_DECIMALS = 3  # mm resolution of generated G-code coordinates
POSITION_TOLERANCE_MM = 0.05  # reported vs commanded position after a wait (M114 has 0.01 mm)
SAFE_LIFT_FEED_MM_MIN = 700.0  # feed of the straight rise after a desync (reference travel feed)

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
_NUMBER = r"(-?\d*\.?\d+)(?=\s|$)"  # a plain decimal, then a space or the end
_POSITION_RE = re.compile(rf"X:\s*{_NUMBER}\s+Y:\s*{_NUMBER}\s+Z:\s*{_NUMBER}")
_NAN3 = (math.nan, math.nan, math.nan)

Point = tuple[float, float, float]


def parse_position(lines: list[str]) -> Point | None:
    """(x, y, z) mm from an ``M114`` report (``X:1.00 Y:2.00 Z:3.00 E:0.00 Count ...``);
    None when no line holds three plain numbers there."""
    for line in lines:
        match = _POSITION_RE.search(line.split("Count", 1)[0])
        if match:
            return tuple(float(v) for v in match.groups())  # type: ignore[return-value]
    return None


def _fmt(value: float) -> str:
    text = f"{value:.{COORD_DECIMALS}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def _where(point: Point) -> str:
    return "X={:.3f} Y={:.3f} Z={:.3f}".format(*point)


def _link_counter(name: str, doc: str) -> property:
    """The int counter ``name`` of the printer's :class:`MarlinLink` (0 before a connect)."""
    return property(lambda self: getattr(self._link, name) if self._link else 0, doc=doc)


class MarlinPrinter(DeviceContext):
    """A Marlin printer on a serial port; see the module docstring for the protocol.

    port: serial device (``/dev/ttyUSB0``, ``COM3``, a virtual printer's ``/dev/pts/N``).
    envelope: where the finger may go (printer coordinates, mm).
    timeout_s: how long to wait for an ``ok`` beyond the motion/dwell the command waits for.
    banner_timeout_s: how long :meth:`connect` waits for the boot banner (0: do not wait).
    boot_settle_s: after the banner, boot chatter is over once the line is quiet this long.
    home_timeout_s: how long ``G28`` may take, keep-alives or not.
    busy_timeout_s: how far keep-alives may stretch other commands beyond their expected
        time before the driver gives up (DeviceTimeoutError).
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
        busy_timeout_s: float = BUSY_TIMEOUT_S,
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
        self.busy_timeout_s = float(busy_timeout_s)
        self.boot_settle_s = float(boot_settle_s)
        self.on_command = on_command
        self.name = name or f"printer {port}"
        self.command_log: list[CommandRecord] = []
        self.banner_seen = False
        self._io: SerialLines | None = None
        self._link: MarlinLink | None = None  # kept after close: its counters stay readable
        self._lock = threading.RLock()
        # the commanded position; None until homed (after every connect)
        self._target: Point | None = None
        self._motion_end_mono = 0.0  # host estimate of when queued motion finishes

    # --- lifecycle --------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, wait for the banner, reset line numbers and set absolute mode."""
        if self._io is not None:
            return
        self._io = SerialLines(open_serial(self.port, self.baudrate, device=self.name), self.name)
        self._link = MarlinLink(self._io, self.name, self.port, self.baudrate, self.timeout_s)
        self._target = None  # a board that reset has lost its position: home again
        try:
            self.banner_seen = self._link.wait_for_banner(self.banner_timeout_s, self.boot_settle_s)
            self._link.reset_line_numbers(0)
            self._record("M110 N0", None)
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

    @property
    def connected(self) -> bool:
        return self._io is not None

    @property
    def halted(self) -> bool:
        """True after :meth:`emergency_stop` or a fatal printer error."""
        return self._link is not None and self._link.halted is not None

    @property
    def target(self) -> Point | None:
        """The last commanded position (x, y, z) mm, or None before homing."""
        return self._target

    resend_count = _link_counter(
        "resend_count", "Lines resent on the printer's request (transmission errors)."
    )
    resyncs = _link_counter(
        "resyncs", "Line-number re-synchronisations (``M110``) after lost lines or desyncs."
    )
    extra_oks = _link_counter(
        "extra_oks", "``ok`` lines that answered no command (duplicated or late) and were dropped."
    )
    garbage_lines = _link_counter("garbage_lines", "Unreadable lines received and skipped.")

    # --- motion -----------------------------------------------------------------------
    def home(self) -> Point:
        """``G28`` (home all axes), then read and return the position (x, y, z) mm.

        G28 is not checked against the envelope: make sure homing cannot hit the sensor.
        If it leaves the head below the clear height, rise straight up first:
        ``move(None, None, envelope.z_clear_mm, feed)``.
        """
        self._transact("G28", self.home_timeout_s)
        position = self._read_position(self.timeout_s)
        self._target = position
        self._motion_end_mono = time.monotonic()
        return position

    def move(self, x: float | None, y: float | None, z: float | None, feed_mm_min: float) -> None:
        """Straight move (``G1``, absolute) to x, y, z mm at ``feed_mm_min``; None keeps an axis.

        Returns once the printer has *planned* the move; call :meth:`wait_for_motion` to
        wait for the finger to get there. Raises SafetyError (nothing sent) when the path
        leaves the envelope or the printer has not been homed. If homing leaves the head
        outside the envelope (e.g. at Z=0), the only move allowed from there is straight
        up: ``move(None, None, z_clear, feed)``.
        """
        start = self._target
        if start is None:
            raise SafetyError(self.name, "refused move: position unknown; call home() first")
        target = tuple(float(s if v is None else v) for v, s in zip((x, y, z), start, strict=True))
        self._check_escape(start, target)  # type: ignore[arg-type]
        self.envelope.check_move(start, target, float(feed_mm_min), device=self.name)  # type: ignore[arg-type]
        words = [
            f"{axis}{_fmt(v)}" for axis, v, s in zip("XYZ", target, start, strict=True) if v != s
        ]
        gcode = " ".join(["G1", *words, f"F{_fmt(float(feed_mm_min))}"])
        duration_s = math.dist(start, target) / float(feed_mm_min) * 60.0
        with self._lock:
            quiet = self.timeout_s + self._motion_remaining_s()
            self._transact(gcode, quiet, quiet + self.busy_timeout_s, new_target=target)  # type: ignore[arg-type]
            self._motion_end_mono = max(self._motion_end_mono, time.monotonic()) + duration_s

    def wait_for_motion(self) -> None:
        """``M400``: return once every queued move has finished (see the module docstring)."""
        with self._lock:
            quiet = self.timeout_s + self._motion_remaining_s()
            self._transact("M400", quiet, quiet + self.busy_timeout_s)
            self._settle(quiet)

    def dwell(self, ms: float) -> None:
        """``G4 P<ms>``: the printer finishes queued moves, then pauses ``ms`` milliseconds."""
        if not (math.isfinite(ms) and ms >= 0):
            raise ValueError(f"dwell ms must be a finite number >= 0, got {ms}")
        with self._lock:
            quiet = self.timeout_s + self._motion_remaining_s() + ms / 1000.0
            self._transact(f"G4 P{int(round(ms))}", quiet, quiet + self.busy_timeout_s)
            self._settle(quiet)

    def position(self) -> Point:
        """``M114``: the position (x, y, z) mm the printer reports.

        Real Marlin reports the position of the last *planned* move; call
        :meth:`wait_for_motion` first to be sure the head is there. The virtual printer
        reports the current interpolated position.
        """
        return self._read_position(self.timeout_s + self._motion_remaining_s())

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
        link = self._link
        if self._io is None or link is None:
            raise DeviceNotConnectedError(self.name, "cannot send M112: not connected")
        link.write_raw("M112")
        link.halted = "emergency stop (M112) sent"
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
        quiet = self.timeout_s if timeout_s is None else float(timeout_s)
        return self._transact(text, quiet, quiet + self.busy_timeout_s)

    # --- internals ----------------------------------------------------------------------
    def _motion_remaining_s(self) -> float:
        return max(0.0, self._motion_end_mono - time.monotonic())

    def _check_escape(self, start: Point, target: Point) -> None:
        """From a position the envelope does not allow, only a straight rise may leave."""
        if self.envelope.contains(start) or not self.envelope.contains(target):
            return  # an allowed start, or a target the envelope refuses by name itself
        if start[:2] == target[:2] and target[2] >= start[2]:
            return
        raise SafetyError(
            self.name,
            f"refused move to {_where(target)}: the head is at {_where(start)}, outside the "
            "safety envelope (where homing left it?); from there only a straight rise is "
            "allowed; nothing was sent",
            f"raise Z first: move(None, None, {self.envelope.z_clear_mm:g}, feed_mm_min), "
            "then travel",
        )

    def _read_position(self, quiet_s: float, *, make_safe: bool = True) -> Point:
        lines = self._transact("M114", quiet_s, expect=has_position, make_safe=make_safe)
        position = parse_position(lines)
        if position is None:
            raise PrinterError(
                self.name,
                f"could not read the position from the M114 reply {lines!r}",
                "expected 'X:<mm> Y:<mm> Z:<mm> ...'; is this a Marlin-compatible firmware?",
            )
        return position

    def _settle(self, quiet_s: float) -> None:
        """After a wait: ``M114`` (answered only once the wait is over), and the printer
        must be where the driver sent it."""
        position = self._read_position(quiet_s)
        self._motion_end_mono = time.monotonic()
        target = self._target
        if target is not None and math.dist(position, target) > POSITION_TOLERANCE_MM:
            self._desync(
                f"the printer reports {_where(position)} after its moves ended, but the "
                f"driver commanded {_where(target)} (a move was lost or replayed)"
            )

    def _require_link(self) -> MarlinLink:
        if self._io is None or self._link is None:
            raise DeviceNotConnectedError(
                self.name, "not connected", "call connect() or use 'with MarlinPrinter(...)'"
            )
        return self._link

    def _transact(
        self,
        gcode: str,
        quiet_s: float,
        overall_s: float | None = None,
        *,
        new_target: Point | None = None,
        expect: Callable[[str], bool] | None = None,
        make_safe: bool = True,
    ) -> list[str]:
        """Send one command through the link and log it; see MarlinLink.command."""
        with self._lock:
            link = self._require_link()
            try:
                replies = link.command(gcode, quiet_s, overall_s, expect=expect)
            except PrinterDesyncError as e:
                if not make_safe:
                    raise
                self._desync(e.detail, cause=e)
            if new_target is not None:
                self._target = new_target
            self._record(gcode, self._target)
            return replies

    def _desync(self, detail: str, cause: Exception | None = None) -> NoReturn:
        """Make the head safe, then raise PrinterDesyncError with what happened."""
        done = self._make_safe()
        raise PrinterDesyncError(
            self.name,
            f"{detail}; {done}",
            "printer and host disagreed about which commands ran; check the USB cable and "
            "that no other program talks to the printer; home again before pressing",
        ) from cause

    def _make_safe(self) -> str:
        """Raise the finger straight up to the clear height and re-read the position."""
        start, self._target = self._target, None
        if start is None:
            return "position unknown, the finger was not moved"
        z = max(self.envelope.z_clear_mm, start[2])
        feed = min(SAFE_LIFT_FEED_MM_MIN, self.envelope.max_feed_mm_min)
        quiet = self.timeout_s + abs(z - start[2]) / feed * 60.0
        try:
            self._transact(f"G1 Z{_fmt(z)} F{_fmt(feed)}", self.timeout_s, make_safe=False)
            self._transact("M400", quiet, quiet + self.busy_timeout_s, make_safe=False)
            position = self._read_position(self.timeout_s, make_safe=False)
        except DeviceError as e:
            logger.error("%s: could not raise the finger after a desync: %s", self.name, e)
            return f"raising the finger failed ({e.detail})"
        self._target = position
        self._motion_end_mono = time.monotonic()
        logger.warning("%s: desync: finger raised to Z=%s", self.name, _fmt(z))
        return f"the finger was raised to Z={_fmt(z)}; the printer reports {_where(position)}"

    def _record(self, gcode: str, target: Point | None) -> None:
        t_unix, t_mono = host_now()
        record = CommandRecord(t_unix, t_mono, gcode, *(target if target is not None else _NAN3))
        self.command_log.append(record)
        if self.on_command is not None:
            self.on_command(record)
