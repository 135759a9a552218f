"""The line-numbered, checksummed G-code exchange with a Marlin-style printer.

:class:`MarlinLink` sends one command at a time and waits for its ``ok``. It knows nothing
about motion or safety; :class:`~beadsight.devices.marlin.MarlinPrinter` builds on it.

What each reply means, and what the link does:

* Every command is framed ``N<n> <gcode>*<checksum>`` (checksum = XOR of all bytes before
  ``*``); the next goes only after its ``ok``. Line numbers only grow; :attr:`acked` is the
  last line the printer acknowledged.
* ``Error:<text>`` followed by ``Resend: <r>`` is a transmission error, whatever the text
  (Marlin: ``checksum mismatch``, ``Line Number is not Last Line Number+1``; OctoPrint's
  virtual printer: ``Checksum mismatch``, ``Missing checksum``, ``expected line 15 got 16``):

  - r is the current line: it is resent (at most ``MAX_RESENDS`` times in a row);
  - r is beyond the current line (the printer's count is ahead): re-synchronise;
  - r is a line the printer already acknowledged: **never resent** (that would replay
    motion out of order). The link re-synchronises, then raises
    :class:`~beadsight.devices.base.PrinterDesyncError`.
* No ``ok`` within the command's timeout, or a transmission ``Error:`` with no
  ``Resend:``: the line or its ``ok`` was lost: re-synchronise.
* Re-synchronise: ``N<m> M110 N<m>`` (m: the next unused line number) resets the printer's
  line counter, the current command goes again as line m+1, and a position query
  (``M114``) whose reply carries data absorbs any late ``ok``. At most ``MAX_RESYNCS`` per
  command. The only command ever repeated is the current one, which the driver keeps
  idempotent (absolute moves, waits, queries).
* Any other ``Error:`` fails the command with PrinterError carrying the printer's text;
  ``halted`` / ``kill()`` / ``stopped`` marks the printer halted.
* Keep-alives (``echo:busy: processing``, ``busy:processing``) extend the quiet timeout,
  never past the command's overall deadline (then DeviceTimeoutError, no retry).
* One ``ok`` per command: ``ok`` lines that arrive between commands are counted in
  :attr:`extra_oks` and dropped; while waiting for a reply that must carry data (``expect``,
  e.g. the ``X:`` line of ``M114``), a bare ``ok`` that comes first belongs to an earlier
  command and is dropped too. ``ok N<k>`` (ADVANCED_OK) for an older line is dropped.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NoReturn

from beadsight.devices.base import (
    DeviceTimeoutError,
    PrinterDesyncError,
    PrinterError,
)
from beadsight.devices.serial_port import SerialLines

logger = logging.getLogger(__name__)

MAX_RESENDS = 5  # resend requests for the same line tolerated before giving up
MAX_RESYNCS = 2  # line-number re-synchronisations tolerated per command
REPLY_GRACE_S = 1.0  # after Error:/Resend:, how long the rest of the reply may take
MAX_GCODE_CHARS = 80  # Marlin's MAX_CMD_SIZE is 96 including N<n> and *<checksum>
MAX_GARBAGE_WARNINGS = 5  # warn about this many garbage lines, then count silently
BOOT_CHATTER_MAX_S = 5.0  # after the banner, boot chatter is over after this long at most
TRANSMISSION_TEXTS = ("checksum", "line number", "expected line", "format error")
# ^ 'Error:' texts about the line itself (Marlin's and OctoPrint's wordings)
HALT_TEXTS = ("halted", "kill", "stopped")  # 'Error:' texts after which the printer halts
FENCE_GCODE = "M114"  # the query that proves every earlier reply has arrived
_RESEND_RE = re.compile(r"^(?:resend|rs)\b\s*:?\s*N?(\d+)", re.IGNORECASE)
_OK_LINE_RE = re.compile(r"^N(\d+)\b")  # 'ok N12 P15 B3' (ADVANCED_OK)

Expect = Callable[[str], bool]


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


def has_position(line: str) -> bool:
    """Whether ``line`` is (or claims to be) an ``M114`` position report."""
    return "X:" in line and "Y:" in line


def is_transmission_error(text: str) -> bool:
    low = text.lower()
    return any(marker in low for marker in TRANSMISSION_TEXTS)


@dataclass
class _Outcome:
    """How the wait for one line ended: ok, resend (of ``line``), lost, failed."""

    kind: str
    lines: list[str] = field(default_factory=list)
    line: int | None = None
    error: str = ""


class _Reply:
    """The lines that arrived in answer to one command line, and what they mean."""

    def __init__(self, n: int, expect: Expect | None):
        self.n = n
        self.expect = expect
        self.lines: list[str] = []
        self.errors: list[str] = []
        self.resend: int | None = None
        self.data_seen = expect is None
        self.early_oks = 0
        self.grace_until: float | None = None  # set once Error:/Resend: came, until the rest

    def _grace(self) -> None:
        self.grace_until = time.monotonic() + REPLY_GRACE_S

    def add_line(self, line: str) -> None:
        self.lines.append(line)
        if self.expect is not None and self.expect(line):
            self.data_seen = True

    def on_error(self, text: str) -> None:
        self.errors.append(text)
        self._grace()

    def on_resend(self, number: int) -> None:
        self.resend = number
        self._grace()

    def on_ok(self, rest: str) -> _Outcome | None:
        """The outcome this ``ok`` completes, or None when it belongs to an earlier line."""
        if self.resend is not None or self.errors:
            return self.settle()
        numbered = _OK_LINE_RE.match(rest)
        if numbered and int(numbered.group(1)) < self.n:
            return None  # ADVANCED_OK for an older line: a late or duplicated ok
        if rest and not numbered and not rest.startswith("P"):
            self.add_line(rest)  # 'ok T:22.0 /0.0', OctoPrint's 'ok X:0.00 Y:...'
        if not self.data_seen:
            self.early_oks += 1  # the ok of an earlier command; the data is still to come
            return None
        return _Outcome("ok", self.lines)

    def settle(self) -> _Outcome:
        """The outcome once the reply has stopped short of a plain ``ok``."""
        error = self.errors[-1] if self.errors else ""
        if self.resend is not None:
            return _Outcome("resend", line=self.resend, error=error)
        if self.errors and is_transmission_error(error):
            return _Outcome("lost", error=error)
        if self.errors:
            return _Outcome("failed", error="', 'Error:".join(self.errors))
        return _Outcome("failed", self.lines, error="the reply carried no data")


class MarlinLink:
    """Numbered, checksummed commands over ``io``; see the module docstring.

    name: device name for messages (``"printer /dev/ttyUSB0"``); port, baudrate: for hints.
    timeout_s: base quiet timeout (also how long one keep-alive extends it).
    Not thread-safe: the printer serialises calls (only :meth:`write_raw` may run beside).
    """

    def __init__(self, io: SerialLines, name: str, port: str, baudrate: int, timeout_s: float):
        self.io = io
        self.name = name
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = float(timeout_s)
        self.next_line = 0
        self.acked = -1  # the last line number the printer acknowledged
        self.resend_count = 0  # lines resent on the printer's request
        self.resyncs = 0  # line-number re-synchronisations (M110) after lost lines/desyncs
        self.extra_oks = 0  # 'ok' lines that answered no command (duplicates, late ones)
        self.garbage_lines = 0  # unreadable lines received and skipped
        self.halted: str | None = None

    # --- public -----------------------------------------------------------------------
    def write_raw(self, text: str) -> None:
        """Send ``text`` as is (no number, no checksum), e.g. ``M112``."""
        self.io.write_line(text)

    def reset_line_numbers(self, number: int | None = None) -> None:
        """``N<m> M110 N<m>``: the printer's next expected line becomes m+1 (m: ``number``,
        default the next unused one)."""
        m = self.next_line if number is None else int(number)
        self.next_line = m + 1
        gcode = f"M110 N{m}"
        framed = frame_line(m, gcode)
        self.io.write_line(framed)
        for _ in range(MAX_RESENDS + 1):
            outcome = self._await(gcode, m, self.timeout_s, self.timeout_s, None)
            if outcome.kind == "ok":
                self.acked = m
                return
            if outcome.kind != "resend":  # any resend request is answered by M110 itself
                self._raise_for(gcode, outcome, self.timeout_s)
            self.resend_count += 1
            self.io.write_line(framed)
        raise self._rejected(gcode, "the printer kept rejecting it")

    def command(
        self,
        gcode: str,
        quiet_s: float,
        overall_s: float | None = None,
        *,
        expect: Expect | None = None,
    ) -> list[str]:
        """Send ``gcode`` as the next line and wait for its ``ok``; the lines before it.

        quiet_s: longest wait without any reply; keep-alives extend it up to ``overall_s``
        (default ``quiet_s``) after sending. expect: the reply must include a line for
        which this is true (bare ``ok`` lines before it are someone else's).
        """
        self._check_usable()
        self.drain()
        overall = max(quiet_s, overall_s or 0.0)
        n = self._send_new(gcode)
        resends = resyncs = 0
        while True:
            outcome = self._await(gcode, n, quiet_s, overall, expect)
            if outcome.kind == "ok":
                self.acked = n
                if resyncs and expect is None:
                    self.fence()
                return outcome.lines
            if outcome.kind == "failed":
                self._raise_for(gcode, outcome, quiet_s)
            if outcome.kind == "resend" and outcome.line == n:
                resends += 1
                if resends > MAX_RESENDS:
                    raise self._rejected(gcode, f"last error: {outcome.error or 'resend'}")
                self.resend_count += 1
                self.io.write_line(frame_line(n, gcode))
                continue
            if outcome.kind == "resend" and outcome.line is not None and outcome.line < n:
                self._desync(gcode, outcome.line, n)
            resyncs += 1  # lost, or the printer's count is ahead of ours
            if resyncs > MAX_RESYNCS:
                self._raise_for(gcode, outcome, quiet_s)
            try:
                n = self._resync_and_resend(gcode, outcome)
            except DeviceTimeoutError:
                self._raise_for(gcode, outcome, quiet_s, "; re-synchronising got no answer either")

    def fence(self) -> list[str]:
        """``M114`` whose reply must carry the position: every earlier reply is in."""
        return self.command(FENCE_GCODE, self.timeout_s, expect=has_position)

    def drain(self) -> None:
        """Handle what arrived between commands: stray oks, resets, errors, chatter."""
        while (line := self.io.read_line(0.0)) is not None:
            low = line.lower()
            if low.startswith("ok"):
                self.extra_oks += 1
                logger.debug(
                    "%s: ok that answered no command (%d so far)", self.name, self.extra_oks
                )
            elif low == "start":
                raise self._reset_detected("between commands")
            elif low.startswith(("error:", "!!")):
                text = _error_text(line)
                self._note_halt(text)
                if not is_transmission_error(text):
                    raise PrinterError(self.name, f"printer says 'Error:{text}' (between commands)")
                logger.warning("%s: transmission error between commands: %s", self.name, text)
            elif _is_garbage(line):
                self._garbage(line, "(nothing)")
            else:
                logger.debug("%s: %s", self.name, line)

    def wait_for_banner(self, timeout_s: float, settle_s: float) -> bool:
        """Wait for the boot banner (``start`` or a line naming Marlin), then until the boot
        chatter has been quiet ``settle_s``. False if no banner came."""
        if timeout_s <= 0:
            return False
        deadline = time.monotonic() + timeout_s
        while True:
            line = self.io.read_line(deadline)
            if line is None:
                logger.info(
                    "%s: no start banner within %.1f s; assuming a board that does not reset on connect",
                    self.name,
                    timeout_s,
                )
                return False
            if line.lower() == "start" or "marlin" in line.lower():
                break
        hard_stop = time.monotonic() + BOOT_CHATTER_MAX_S
        while (line := self.io.read_line(min(time.monotonic() + settle_s, hard_stop))) is not None:
            logger.debug("%s boot: %s", self.name, line)
            if time.monotonic() > hard_stop:
                break
        return True

    # --- waiting for one line's reply ----------------------------------------------------
    def _await(
        self, gcode: str, n: int, quiet_s: float, overall_s: float, expect: Expect | None
    ) -> _Outcome:
        """Read replies to line ``n`` until they decide its fate (see the module docstring)."""
        reply = _Reply(n, expect)
        hard_deadline = time.monotonic() + overall_s
        deadline = min(time.monotonic() + quiet_s, hard_deadline)
        busy = False
        while True:
            until = deadline if reply.grace_until is None else min(deadline, reply.grace_until)
            line = self.io.read_line(until)
            if line is None:
                if reply.grace_until is not None or reply.early_oks:
                    return reply.settle()  # a reply that stopped short, or oks without data
                if busy and time.monotonic() >= hard_deadline:
                    raise self._busy_timeout(gcode, overall_s)
                return _Outcome("lost")
            low = line.lower()
            if low.startswith("ok"):
                outcome = reply.on_ok(line[2:].strip())
                if outcome is not None:
                    return outcome
                self.extra_oks += 1
            elif _RESEND_RE.match(line):
                reply.on_resend(int(_RESEND_RE.match(line).group(1)))  # type: ignore[union-attr]
            elif low.startswith(("error:", "!!")):
                text = _error_text(line)
                self._note_halt(text)
                reply.on_error(text)
                logger.warning("%s: printer error on %r: %s", self.name, gcode, text)
            elif low.startswith(("echo:busy", "busy:")):
                busy = True
                deadline = min(max(deadline, time.monotonic() + self.timeout_s), hard_deadline)
            elif low == "start":
                raise self._reset_detected(f"while waiting for {gcode!r}")
            elif _is_garbage(line):
                self._garbage(line, gcode)
            elif low.startswith(("echo:", "//")) or low == "wait":
                self._echo(line, gcode)
            else:
                reply.add_line(line)

    # --- recovery ------------------------------------------------------------------------
    def _send_new(self, gcode: str) -> int:
        n = self.next_line
        self.next_line = n + 1
        self.io.write_line(frame_line(n, gcode))
        return n

    def _resync_and_resend(self, gcode: str, outcome: _Outcome) -> int:
        why = (
            f"the printer asked for line {outcome.line}, ahead of ours"
            if outcome.kind == "resend"
            else f"no 'ok' ({outcome.error or 'no reply'})"
        )
        logger.warning("%s: %s for %r; re-synchronising line numbers", self.name, why, gcode)
        self.reset_line_numbers()
        self.resyncs += 1
        return self._send_new(gcode)

    def _desync(self, gcode: str, asked: int, current: int) -> None:
        detail = (
            f"printer asked to resend line {asked}, which it had already acknowledged "
            f"(waiting for line {current}, {gcode!r}); nothing was resent"
        )
        try:
            self.reset_line_numbers()
            self.resyncs += 1
            detail += "; line numbers re-synchronised"
        except (PrinterError, DeviceTimeoutError) as e:
            detail += f"; re-synchronising failed too ({e.detail})"
        raise PrinterDesyncError(
            self.name,
            detail,
            "printer and host disagree about which commands ran: check the USB cable and "
            "that nothing else talks to the printer, then home again",
        )

    # --- errors --------------------------------------------------------------------------
    def _check_usable(self) -> None:
        if self.halted is not None:
            raise PrinterError(
                self.name,
                f"printer is halted ({self.halted})",
                "reset or power-cycle it, then reconnect",
            )

    def _raise_for(self, gcode: str, outcome: _Outcome, quiet_s: float, note: str = "") -> NoReturn:
        if outcome.kind == "failed":
            if outcome.error == "the reply carried no data":
                raise PrinterError(
                    self.name, f"the reply to {gcode!r} carried no data: {outcome.lines!r}"
                )
            raise PrinterError(self.name, f"{gcode!r} failed: printer says 'Error:{outcome.error}'")
        if outcome.kind == "resend":
            raise self._rejected(gcode, f"the printer kept asking for line {outcome.line}")
        extra = f"; last printer error: {outcome.error}" if outcome.error else ""
        raise DeviceTimeoutError(
            self.name,
            f"no 'ok' for {gcode!r} within {quiet_s:.1f} s{extra}{note}",
            f"is the printer on and is {self.baudrate} its baud rate? "
            f"Close other programs using {self.port} (OctoPrint, Pronterface)",
        )

    def _rejected(self, gcode: str, why: str) -> PrinterError:
        return PrinterError(
            self.name,
            f"{gcode!r} was rejected {MAX_RESENDS} times ({why})",
            "check the USB cable and that the baud rate matches the printer",
        )

    def _busy_timeout(self, gcode: str, overall_s: float) -> DeviceTimeoutError:
        return DeviceTimeoutError(
            self.name,
            f"{gcode!r} did not finish within its overall limit of {overall_s:.1f} s: "
            "the printer kept answering 'busy' but never 'ok'",
            "the printer may be stuck waiting (filament change, heating, user prompt); check its screen",
        )

    def _reset_detected(self, when: str) -> PrinterError:
        self.next_line = 0
        self.acked = -1
        return PrinterError(
            self.name,
            f"printer restarted ('start') {when}; its position is lost",
            "check the power supply and USB cable, then reconnect and home again",
        )

    def _note_halt(self, text: str) -> None:
        if any(word in text.lower() for word in HALT_TEXTS):
            self.halted = f"printer says 'Error:{text}'"

    def _echo(self, line: str, gcode: str) -> None:
        if "unknown command" in line.lower():
            logger.warning("%s: %s (sent %r)", self.name, line, gcode)
        else:
            logger.debug("%s: %s", self.name, line)

    def _garbage(self, line: str, gcode: str) -> None:
        self.garbage_lines += 1
        if self.garbage_lines <= MAX_GARBAGE_WARNINGS:
            logger.warning(
                "%s: skipped unreadable line %r (waiting for %r)", self.name, line[:40], gcode
            )


def _error_text(line: str) -> str:
    return line.split(":", 1)[1].strip() if ":" in line else line.lstrip("!").strip()


def _is_garbage(line: str) -> bool:
    return "\ufffd" in line or not line.isprintable()
