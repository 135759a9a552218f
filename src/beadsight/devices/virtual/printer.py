"""A virtual Marlin printer on a pseudo-terminal, with motion in simulated time.

What it models (enough for :class:`~beadsight.devices.marlin.MarlinPrinter` to run
its real code path against it):

* Boot: when the host opens the port the board "resets"; after ``boot_delay_s`` it
  prints ``start`` and a few ``echo:`` lines (``banner=False``: a board that does not
  reset and prints nothing).
* Lines: optional ``N<n> ... *<checksum>`` framing checked like Marlin (checksum
  mismatch, missing checksum, out-of-order line number -> ``Error:...``, ``Resend: n``,
  ``ok``); ``M110 N<n>`` sets the line number; ``M112`` halts at once.
  ``error_style="octoprint"`` words these errors as OctoPrint's virtual printer does
  (``Error: Checksum mismatch``, ``Error: expected line 15 got 16``, ``Resend:15``) and
  answers ``M114`` on the ``ok`` line (``ok X:.. Y:.. Z:..``).
* Motion: ``G0``/``G1`` (absolute or ``G91`` relative, modal ``F`` in mm/min) are
  planned into a 16-block buffer and acknowledged once planned (later when the buffer
  is full); each block runs at constant speed = its feed rate, one after the other.
  ``M400`` answers when motion has ended, ``G4 P<ms>``/``S<s>`` after motion plus the
  dwell, ``G28`` after a straight move to ``home_position_mm``. ``M114`` reports the
  current *interpolated* position. Waiting commands send ``echo:busy: processing``
  every ``busy_interval_s``.
* Faults to inject (thread-safe, from the test): :meth:`set_silent`,
  :meth:`set_garbage_replies`, :meth:`emit_garbage`, :meth:`fail_next`,
  :meth:`corrupt_next`, :meth:`busy_next` (``math.inf``: busy forever), :meth:`unplug`,
  and the misbehaviours of a confused or noisy board: :meth:`reject_next` (a resend
  request for the line itself, an acknowledged line or one not sent yet; an error with no
  resend), :meth:`lose_next` (a line or an ``ok`` lost), :meth:`duplicate_ok_next`,
  :meth:`m114_reply_next` (a malformed position report).

All durations are simulated seconds (see :class:`SimClock`).
"""

from __future__ import annotations

import logging
import random
import re
import threading
from collections import deque
from dataclasses import dataclass

from beadsight.devices.clock import SimClock
from beadsight.devices.marlin_link import checksum
from beadsight.devices.virtual.motion import MotionPlan, Vec3
from beadsight.devices.virtual.pty_device import PtyDevice

logger = logging.getLogger(__name__)

PLANNER_BLOCKS = 16  # Marlin's BLOCK_BUFFER_SIZE: planned moves waiting to run
BUSY_INTERVAL_S = 2.0  # Marlin's DEFAULT_KEEPALIVE_INTERVAL
BOOT_DELAY_S = 0.2  # reset -> 'start' (a real board takes ~1-2 s)
HOMING_FEED_MM_MIN = 3000.0  # speed of the simulated homing move
DEFAULT_FEED_MM_MIN = 1000.0  # feed before any F word
HOME_POSITION_MM = (0.0, 0.0, 180.0)  # where G28 leaves the head
STEPS_PER_MM = (80.0, 80.0, 400.0)  # only for the 'Count' part of the M114 report
BANNER = (
    "start",
    "echo:Marlin 2.1.2 (beadsight virtual printer)",
    "echo: Last Updated: 2024-01-01 | Author: (beadsight)",
    "echo: Free Memory: 4096  PlannerBufferBytes: 1232",
    "echo:Hardcoded Default Settings Loaded",
)
ERROR_STYLES = {
    "marlin": {
        "checksum": "Error:checksum mismatch, Last Line: {last}",
        "no_checksum": "Error:No Checksum with line number, Last Line: {last}",
        "no_number": "Error:No Line Number with checksum, Last Line: {last}",
        "number": "Error:Line Number is not Last Line Number+1, Last Line: {last}",
        "resend": "Resend: {line}",
    },
    "octoprint": {  # the texts of OctoPrint's bundled virtual printer
        "checksum": "Error: Checksum mismatch",
        "no_checksum": "Error: Missing checksum",
        "no_number": "Error: No Line Number with checksum, Last Line: {last}",
        "number": "Error: expected line {line} got {got}",
        "resend": "Resend:{line}",
    },
}
_LINE_RE = re.compile(r"^N(-?\d+)\s*(.*)$")
_WORD_RE = re.compile(r"([A-Za-z])\s*(-?\d*\.?\d+)")
_ACCEPTED = set("M17 M18 M84 M104 M106 M107 M140 M211 M220 M221 M82 M83".split())
_SILENT = set("G0 G1 G4 G28 G90 G91 G92 M400".split())  # run without a reply but 'ok'


@dataclass
class _Pending:
    gcode: str
    ready_at: float = 0.0  # simulated time before which the command may not start (busy fault)
    wait_until: float | None = None  # set once started, for commands that finish later
    last_busy: float | None = None  # simulated time of the last keep-alive


class VirtualPrinter(PtyDevice):
    """Virtual Marlin printer; open :attr:`port` with :class:`MarlinPrinter`.

    home_position_mm: where ``G28`` takes the head; start_position_mm: the head's
    position at power-on (default: the home position).
    """

    def __init__(
        self,
        *,
        clock: SimClock | None = None,
        time_scale: float = 1.0,
        home_position_mm: Vec3 = HOME_POSITION_MM,
        start_position_mm: Vec3 | None = None,
        banner: bool = True,
        boot_delay_s: float = BOOT_DELAY_S,
        busy_interval_s: float = BUSY_INTERVAL_S,
        homing_feed_mm_min: float = HOMING_FEED_MM_MIN,
        error_style: str = "marlin",
        seed: int = 0,
        name: str = "virtual printer",
    ):
        if error_style not in ERROR_STYLES:
            raise ValueError(
                f"error_style must be one of {sorted(ERROR_STYLES)}, got {error_style!r}"
            )
        super().__init__(name, clock if clock is not None else SimClock(time_scale))
        self.error_style = error_style
        self.home_position_mm = tuple(float(v) for v in home_position_mm)
        self.banner = banner
        self.boot_delay_s = float(boot_delay_s)
        self.busy_interval_s = float(busy_interval_s)
        self.homing_feed_mm_min = float(homing_feed_mm_min)
        self.received: list[str] = []  # every line the host sent, as received
        self.executed: list[str] = []  # every command executed (acknowledged), without framing
        self.replies: list[str] = []  # every line sent to the host (keep-alives excepted)
        self.halted = False
        self._rng = random.Random(seed)
        self._lock = threading.RLock()  # guards motion state and faults
        start = start_position_mm if start_position_mm is not None else home_position_mm
        self._motion = MotionPlan(start)
        self._queue: deque[_Pending] = deque()
        self._boot_at: float | None = None
        self._last_n = 0
        self._relative = False
        self._feed_mm_min = DEFAULT_FEED_MM_MIN
        # faults
        self._silent = False
        self._garbage_replies = False
        self._garbage_to_emit = 0
        self._fail_next: tuple[str, bool] | None = None
        self._corrupt_next = 0
        self._busy_next_s = 0.0
        self._reject: tuple[str | None, int | None, bool] | None = None
        self._lose: str | None = None
        self._duplicate_ok = False
        self._held_ok = False
        self._m114_reply: str | None = None

    # --- world interface --------------------------------------------------------------
    def position_at(self, t_sim: float) -> Vec3:
        """The head position (x, y, z) mm at simulated time ``t_sim``."""
        with self._lock:
            return self._motion.position_at(t_sim)

    def current_position(self) -> Vec3:
        return self.position_at(self.clock.now())

    # --- faults -----------------------------------------------------------------------
    def set_silent(self, silent: bool = True) -> None:
        """Read commands but never answer (a hung board or the wrong baud rate)."""
        with self._lock:
            self._silent = silent

    def set_garbage_replies(self, garbage: bool = True) -> None:
        """Answer every command with unreadable bytes instead of ``ok``."""
        with self._lock:
            self._garbage_replies = garbage

    def emit_garbage(self, lines: int = 3) -> None:
        """Send ``lines`` unreadable lines now (line noise); commands still get their ok."""
        with self._lock:
            self._garbage_to_emit += lines

    def fail_next(
        self, text: str = "MINTEMP triggered, system stopped! Heater_ID: 0", halt: bool = True
    ) -> None:
        """The next command gets ``Error:<text>`` and no ``ok``; ``halt`` stops the board."""
        with self._lock:
            self._fail_next = (text, halt)

    def corrupt_next(self, lines: int = 1) -> None:
        """The next ``lines`` received lines fail their checksum (noise on the wire)."""
        with self._lock:
            self._corrupt_next += lines

    def busy_next(self, seconds: float) -> None:
        """Hold the next command ``seconds`` before running it, sending busy keep-alives."""
        with self._lock:
            self._busy_next_s = float(seconds)

    def reject_next(
        self, error: str | None = None, *, resend: int | None = 0, ok: bool = True
    ) -> None:
        """Answer the next numbered line as a transmission error without running it.

        Replies ``error`` (default: the style's line-number error), then, unless ``resend``
        is None, a resend request for line n + ``resend`` (0: the line itself; -3: a line
        acknowledged three lines ago, as a board that lost its place; +1: a line not sent
        yet, as OctoPrint's noisy-line simulation), then ``ok`` unless ``ok`` is False.
        The board's line counter becomes n + ``resend`` - 1 (unchanged when None).
        """
        with self._lock:
            self._reject = (error, resend, ok)

    def lose_next(self, what: str = "line") -> None:
        """Lose the next line (``"line"``: it never reaches the firmware) or its ``ok``
        (``"ok"``: the command runs, the answer is lost)."""
        if what not in ("line", "ok"):
            raise ValueError(f"lose_next takes 'line' or 'ok', got {what!r}")
        with self._lock:
            self._lose = what

    def duplicate_ok_next(self) -> None:
        """Answer the next command with two oks; the second is sent as the next line arrives."""
        with self._lock:
            self._duplicate_ok = True

    def m114_reply_next(self, text: str) -> None:
        """Answer the next ``M114`` with ``text`` (then ``ok``) instead of the position."""
        with self._lock:
            self._m114_reply = text

    # --- pty hooks ----------------------------------------------------------------------
    def on_host_open(self) -> None:
        with self._lock:
            self._queue.clear()
            self._last_n = 0
            if self.banner:  # the board resets when the port opens (DTR), then boots
                self.halted = False
                self._motion.stop(self.clock.now())
                self._boot_at = self.clock.now() + self.boot_delay_s

    def on_line(self, line: str) -> None:
        with self._lock:
            self.received.append(line)
            if self._boot_at is not None or self.halted:
                return  # booting (bootloader eats input) or halted (ignores everything)
            if _is_m112(line):
                self._halt("Printer halted. kill() called!")
                return
            if self._held_ok:  # a duplicated ok, late enough to meet the host's next line
                self._held_ok = False
                self._reply("ok")
            if self._silent:
                return
            if self._lose == "line":
                self._lose = None
                return
            gcode = self._check_framing(line)
            if gcode is not None:
                self._queue.append(_Pending(gcode, ready_at=self.clock.now() + self._busy_next_s))
                self._busy_next_s = 0.0

    def on_tick(self) -> None:
        with self._lock:
            now = self.clock.now()
            if self._boot_at is not None:
                if now < self._boot_at:
                    return
                self._boot_at = None
                for text in BANNER:
                    self.write_line(text)
            while self._garbage_to_emit > 0:
                self._garbage_to_emit -= 1
                self.write_raw(self._garbage_bytes())
            self._motion.prune(now)
            while self._queue and not self.halted:
                if not self._step_head(self._queue[0], now):
                    break
                if self._queue:  # a halt while stepping empties the queue
                    self._queue.popleft()

    # --- line framing ----------------------------------------------------------------
    def _check_framing(self, line: str) -> str | None:
        """The command inside ``line``, or None after answering a transmission error."""
        match = _LINE_RE.match(line)
        if match is None:
            if "*" in line:
                return self._line_error("no_number", None)
            return line.strip()
        n = int(match.group(1))
        if self._reject is not None:
            return self._rejected(n)
        body, star, cs_text = line.partition("*")
        if not star:
            return self._line_error("no_checksum", n)
        corrupted = self._corrupt_next > 0
        if corrupted:
            self._corrupt_next -= 1
        if corrupted or not cs_text.strip().isdigit() or checksum(body) != int(cs_text):
            return self._line_error("checksum", n)
        command = match.group(2).partition("*")[0].strip()
        is_m110 = command.split()[:1] == ["M110"]
        if n != self._last_n + 1 and not is_m110:
            return self._line_error("number", n)
        self._last_n = n
        return command

    def _error_text(self, kind: str, got: int | None, line: int | None = None) -> str:
        expected = self._last_n + 1 if line is None else line
        return ERROR_STYLES[self.error_style][kind].format(
            last=self._last_n, line=expected, got=got
        )

    def _line_error(self, kind: str, got: int | None) -> None:
        self._reply(self._error_text(kind, got))
        self._reply(self._error_text("resend", got))
        self._reply("ok")
        return None

    def _rejected(self, n: int) -> None:
        error, resend, ok = self._reject  # type: ignore[misc]
        self._reject = None
        if resend is not None:
            self._last_n = n + resend - 1
        self._reply(error if error is not None else self._error_text("number", n))
        if resend is not None:
            self._reply(self._error_text("resend", n, n + resend))
        if ok:
            self._reply("ok")
        return None

    # --- execution --------------------------------------------------------------------
    def _step_head(self, cmd: _Pending, now: float) -> bool:
        """Advance the command at the head of the queue; True once it is done (acked)."""
        if now < cmd.ready_at:
            self._keepalive(cmd, now)
            return False
        if self._fail_next is not None:
            text, halt = self._fail_next
            self._fail_next = None
            self._reply(f"Error:{text}")
            if halt:
                self._halt("Printer halted. kill() called!")
            return True
        if cmd.wait_until is None:
            result = self._start(cmd, now)
            if result is None:  # cannot start yet (planner full / motion running)
                self._keepalive(cmd, now)
                return False
            cmd.wait_until = result
        if now < cmd.wait_until:
            self._keepalive(cmd, now)
            return False
        self._finish(cmd, now)
        return True

    def _keepalive(self, cmd: _Pending, now: float) -> None:
        """'echo:busy: processing' every busy_interval_s while ``cmd`` blocks the queue."""
        if cmd.last_busy is None:
            cmd.last_busy = now
        elif now - cmd.last_busy >= self.busy_interval_s:
            self._reply("echo:busy: processing")
            cmd.last_busy = now

    def _start(self, cmd: _Pending, now: float) -> float | None:
        """Start ``cmd``; returns when it completes (simulated s) or None to retry later."""
        word, args = _parse(cmd.gcode)
        if word in ("G0", "G1"):
            if self._motion.pending(now) >= PLANNER_BLOCKS:
                return None
            self._plan_move(args, now)
            return now
        if word in ("M400", "G4", "G28", "G92") and self._motion.end() > now:
            return None  # these wait for the planner to empty
        if word == "G4":
            return now + args.get("P", 0.0) / 1000.0 + args.get("S", 0.0)
        if word == "G28":
            return self._motion.add(now, self.home_position_mm, self.homing_feed_mm_min)
        if word == "G92":
            here = self._motion.position_at(now)
            self._motion.stop(now, tuple(args.get(a, v) for a, v in zip("XYZ", here, strict=True)))  # type: ignore[arg-type]
        elif word == "G90":
            self._relative = False
        elif word == "G91":
            self._relative = True
        return now

    def _finish(self, cmd: _Pending, now: float) -> None:
        word, args = _parse(cmd.gcode)
        self.executed.append(cmd.gcode)
        if word == "M114":
            if self._report_position(now):
                return
        elif word == "M105":
            self._ok("ok T:22.0 /0.0 B:22.0 /0.0 @:0 B@:0")
            return
        elif word == "M115":
            self._reply(
                "FIRMWARE_NAME:Marlin 2.1.2 (beadsight virtual printer) SOURCE_CODE_URL:none PROTOCOL_VERSION:1.0"
            )
        elif word == "M110":
            self._last_n = int(args.get("N", self._last_n))
        elif word not in _ACCEPTED and word not in _SILENT:
            self._reply(f'echo:Unknown command: "{cmd.gcode}"')
        self._ok()

    def _ok(self, text: str = "ok") -> None:
        """The command's ok, unless a fault loses or duplicates it."""
        if self._lose == "ok":
            self._lose = None
            return
        self._reply(text)
        if self._duplicate_ok:
            self._duplicate_ok = False
            self._held_ok = True

    def _report_position(self, now: float) -> bool:
        """Answer M114; True when the report went out on the ok line (OctoPrint style)."""
        if self._m114_reply is not None:
            text, self._m114_reply = self._m114_reply, None
            self._reply(text)
            return False
        x, y, z = self.position_at(now)
        if self.error_style == "octoprint":
            self._ok(f"ok X:{x} Y:{y} Z:{z} E:0.0 Count: A:{int(x * 100)} B:{int(y * 100)}")
            return True
        counts = " ".join(
            f"{a}:{round(v * s)}" for a, v, s in zip("XYZ", (x, y, z), STEPS_PER_MM, strict=True)
        )
        self._reply(f"X:{x:.2f} Y:{y:.2f} Z:{z:.2f} E:0.00 Count {counts}")
        return False

    def _plan_move(self, args: dict[str, float], now: float) -> None:
        if "F" in args:
            self._feed_mm_min = args["F"]
        base = self._motion.last_point()
        target = tuple(
            (b + args[a] if self._relative else args[a]) if a in args else b
            for a, b in zip("XYZ", base, strict=True)
        )
        self._motion.add(now, target, self._feed_mm_min)  # type: ignore[arg-type]

    def _halt(self, text: str) -> None:
        self._motion.stop(self.clock.now())
        self._queue.clear()
        self._reply(f"Error:{text}")
        self.halted = True
        logger.info("%s halted: %s", self.name, text)

    def _reply(self, text: str) -> None:
        if not text.startswith("echo:busy"):
            self.replies.append(text)
        if self._garbage_replies and not text.startswith("echo:busy"):
            self.write_raw(self._garbage_bytes())
        else:
            self.write_line(text)

    def _garbage_bytes(self) -> bytes:
        size = self._rng.randint(3, 20)
        return bytes(self._rng.choice(range(128, 256)) for _ in range(size)) + b"\r\n"


def _is_m112(line: str) -> bool:
    """Marlin's emergency parser acts on M112 as soon as it arrives, framed or not."""
    tokens = line.partition("*")[0].split()
    if tokens and tokens[0].upper().startswith("N"):
        tokens = tokens[1:]
    return tokens[:1] == ["M112"]


def _parse(gcode: str) -> tuple[str, dict[str, float]]:
    """('G1', {'X': 1.0, 'F': 700.0}) from 'G1 X1 F700'."""
    parts = gcode.split(None, 1)
    word = parts[0].upper() if parts else ""
    args = {
        m.group(1).upper(): float(m.group(2))
        for m in _WORD_RE.finditer(parts[1] if len(parts) > 1 else "")
    }
    return word, args
