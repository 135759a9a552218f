"""MarlinPrinter against OctoPrint's virtual printer, an independent Marlin emulator.

OctoPrint's bundled ``virtual_printer`` plugin is what printer hosts test against; it has
its own error texts (``Error: expected line 15 got 16``, ``Error: Missing checksum``),
fault injection (``!!DEBUG:...``) and, by default, transmission errors at lines 100, 105,
110 and 115. ``benchmarks/octoprint_bridge.py`` serves it on a pty; this script runs a
short press session through it with the real driver and prints each step ok / FAILED.

OctoPrint pins many packages, so it has a venv of its own: ``scripts/setup.sh --dev`` makes
``.venv-octoprint/``, used by default; ``--octoprint-python PATH`` or
``BEADSIGHT_OCTOPRINT_PYTHON`` names another::

    .venv/bin/python benchmarks/octoprint_peer.py

Steps: connect, home (OctoPrint homes to 0,0,0: the driver must rise straight up
first), presses at ten points (they cross lines 100-115), then one fault per step: a
duplicated ``ok`` before a slow move, a line the printer drops (``dont_answer``), an
error without a resend request (``trigger_missing_lineno``), noisy lines
(``resend_ratio 10``), resend requests for an already acknowledged line
(``trigger_resend_checksum`` / ``_lineno``, ``trigger_missing_checksum``: the driver must
raise a PrinterError without replaying the line and leave the finger at the clear height,
then press on), a printer busy forever (``M600`` with keep-alives: a timeout, not a hang),
and a fatal error (``Error:...Printer halted``). After a failed step the
session reconnects and homes, so that each fault is tried on its own; a step that hangs
for ``STEP_TIMEOUT_S`` fails, and the steps after it are not run. Exit status 1 if any
step failed.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

from beadsight.devices import (
    DeviceTimeoutError,
    MarlinPrinter,
    PrinterError,
    SafetyEnvelope,
)
from beadsight.inference.machine import cpu_summary

BRIDGE = Path(__file__).with_name("octoprint_bridge.py")
ENV_VAR = "BEADSIGHT_OCTOPRINT_PYTHON"
SETUP_VENV = Path(__file__).resolve().parents[1] / ".venv-octoprint" / "bin" / "python"
ENVELOPE = SafetyEnvelope(
    centre_xy_mm=(30.0, 30.0), xy_half_range_mm=15.0, z_floor_mm=2.0, z_clear_mm=10.0
)  # OctoPrint's virtual printer homes to (0, 0, 0); the "sensor" sits at (30, 30)
PRESS_Z_MM = 4.5
TRAVEL_FEED = 3000.0  # mm/min
PRESS_FEED = 600.0  # mm/min
DWELL_MS = 100.0
TOLERANCE_MM = 0.01  # reported vs commanded position
OCTOPRINT_TIME_FACTOR = 0.1  # the virtual printer sleeps 0.1 x a move's duration ...
OCTOPRINT_SLEEP_SLICE_S = 0.05  # ... in slices of its read timeout, the last one skipped
SLOW_FEED = 300.0  # mm/min, the move in the duplicated-ok step
TIMEOUT_S = 2.0  # the driver's ok timeout (short: lost lines are part of the test)
BUSY_TIMEOUT_S = 3.0  # the driver's limit for keep-alives beyond the expected time
STEP_TIMEOUT_S = 60.0  # a step still running after this is a hang
SETTINGS = {"sendBusy": True, "busyInterval": 0.2}  # keep-alives during G4 and M600
OFFSETS = [(-10, -10), (0, -10), (10, -10), (-10, 0), (0, 0), (10, 0), (-10, 10), (0, 10)]


class Peer:
    """The bridge process: OctoPrint's virtual printer on a pty."""

    def __init__(self, python: str, log_path: Path):
        self.log_path = log_path
        sets = [arg for k, v in SETTINGS.items() for arg in ("--set", f"{k}={json.dumps(v)}")]
        self.proc = subprocess.Popen(
            [python, str(BRIDGE), "--log", str(log_path), *sets],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.version = self._expect("VERSION")
        self.port = self._expect("PORT")

    def _expect(self, word: str) -> str:
        line = self.proc.stdout.readline()  # type: ignore[union-attr]
        if not line.startswith(word + " "):
            raise RuntimeError(f"octoprint bridge said {line!r}, expected {word} ...")
        return line.split(" ", 1)[1].strip()

    def control(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")  # type: ignore[union-attr]
        self.proc.stdin.flush()  # type: ignore[union-attr]
        self._expect_done()

    def _expect_done(self) -> None:
        line = self.proc.stdout.readline()  # type: ignore[union-attr]
        if line.strip() != "DONE":
            raise RuntimeError(f"octoprint bridge said {line!r}, expected DONE")

    def received(self) -> list[str]:
        return self.log_path.read_text().splitlines()

    def close(self) -> None:
        try:
            self.proc.stdin.write("QUIT\n")  # type: ignore[union-attr]
            self.proc.stdin.flush()  # type: ignore[union-attr]
            self.proc.wait(5)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()


class Session:
    """Press steps on the printer, each checking the position the printer reports."""

    def __init__(self, peer: Peer, printer: MarlinPrinter):
        self.peer = peer
        self.printer = printer
        self.z_clear = ENVELOPE.z_clear_mm

    def point(self, index: int) -> tuple[float, float]:
        dx, dy = OFFSETS[index % len(OFFSETS)]
        cx, cy = ENVELOPE.centre_xy_mm
        return cx + dx, cy + dy

    def wait(self, target: tuple[float, float, float]) -> None:
        self.printer.wait_for_motion()
        got = self.printer.position()
        if math.dist(got, target) > TOLERANCE_MM:
            raise AssertionError(f"printer reports {got} after the wait, commanded {target}")

    def travel(self, index: int) -> tuple[float, float]:
        x, y = self.point(index)
        self.printer.move(x, y, self.z_clear, TRAVEL_FEED)
        self.wait((x, y, self.z_clear))
        return x, y

    def press(self, index: int) -> None:
        x, y = self.travel(index)
        self.printer.move(None, None, PRESS_Z_MM, PRESS_FEED)
        self.wait((x, y, PRESS_Z_MM))
        self.printer.dwell(DWELL_MS)
        self.printer.move(None, None, self.z_clear, TRAVEL_FEED)
        self.wait((x, y, self.z_clear))

    def reconnect(self) -> None:
        self.printer.close()
        self.printer.connect()
        self.printer.home()
        self.printer.move(None, None, self.z_clear, TRAVEL_FEED)
        self.travel(4)

    def desync(self, trigger: str, index: int) -> str:
        """The printer asks again for the acknowledged descent: never replay it."""
        self.travel(index)
        descend = f"G1 Z{PRESS_Z_MM:g} F{PRESS_FEED:g}"
        self.printer.move(None, None, PRESS_Z_MM, PRESS_FEED)
        mark = len(self.peer.received())
        self.peer.control(f"DEBUG {trigger}")
        try:
            self.printer.wait_for_motion()
        except PrinterError as e:
            error = e
        else:
            raise AssertionError("no error: the printer asked for an acknowledged line")
        replayed = [line for line in self.peer.received()[mark:] if descend in line]
        if replayed:
            raise AssertionError(f"the acknowledged line was sent again: {replayed}")
        z = self.printer.position()[2]
        if z < self.z_clear - TOLERANCE_MM:
            raise AssertionError(f"finger left at Z={z} after: {error}")
        return f"{type(error).__name__}, finger at Z={z:g}"

    def duplicated_ok(self) -> str:
        x, y = self.travel(0)
        distance = 25.0
        self.peer.control("DUPOK")  # the move's ok comes twice, the copy with the M400
        start = time.monotonic()
        self.printer.move(x + distance, y, self.z_clear, SLOW_FEED)
        self.printer.wait_for_motion()
        took = time.monotonic() - start
        needed = distance / SLOW_FEED * 60.0 * OCTOPRINT_TIME_FACTOR - OCTOPRINT_SLEEP_SLICE_S
        if took < needed:
            raise AssertionError(
                f"wait_for_motion returned after {took:.2f} s; the move takes {needed:.2f} s"
            )
        return f"waited {took:.2f} s for a {needed:.2f} s move"

    def busy_forever(self) -> str:
        start = time.monotonic()
        try:
            self.printer.send("M600")  # filament change: 'echo:busy paused for user' forever
        except DeviceTimeoutError as e:
            return f"DeviceTimeoutError after {time.monotonic() - start:.1f} s ({e.detail[:60]}...)"
        raise AssertionError("M600 returned while the printer was still busy")

    def fatal(self) -> str:
        self.peer.control("DEBUG trigger_fatal_error_marlin")
        time.sleep(0.2)
        try:
            self.printer.send("M105")
        except PrinterError as e:
            if "Thermal Runaway" not in str(e) and "halted" not in str(e):
                raise AssertionError(f"unexpected error {e}") from None
        else:
            raise AssertionError("no error after 'Error:Printer halted'")
        try:
            self.printer.send("M105")
        except PrinterError as e:
            return f"halted: {e.detail[:50]}"
        raise AssertionError("commands still accepted after the printer halted")


def steps(session: Session, presses: int) -> list[tuple[str, Callable[[], object]]]:
    p, peer = session.printer, session.peer
    out: list[tuple[str, Callable[[], object]]] = [
        ("connect (M110 N0, G90)", p.connect),
        ("home (G28) -> 0, 0, 0", p.home),
        ("heaters off", p.heaters_off),
        ("rise straight up from Z=0", lambda: p.move(None, None, session.z_clear, TRAVEL_FEED)),
        ("travel over the sensor", lambda: session.travel(4)),
    ]
    out += [
        (f"press {i + 1} (lines {13 * i + 10}..)", lambda i=i: session.press(i))
        for i in range(presses)
    ]

    def with_fault(command: str, index: int) -> Callable[[], object]:
        return lambda: (peer.control(f"DEBUG {command}"), session.press(index))

    def noisy() -> None:
        peer.control("DEBUG resend_ratio 10")
        try:
            session.press(1)
            session.press(2)
        finally:
            peer.control("DEBUG resend_ratio 0")  # a reset keeps it: switch it off here

    out += [
        ("duplicated ok: wait_for_motion waits for the move", session.duplicated_ok),
        ("line dropped (dont_answer)", with_fault("dont_answer", 3)),
        ("error without resend (trigger_missing_lineno)", with_fault("trigger_missing_lineno", 5)),
        ("noisy line (resend_ratio 10), two presses", noisy),
    ]
    for i, trigger in enumerate(
        ("trigger_resend_checksum", "trigger_resend_lineno", "trigger_missing_checksum")
    ):
        out.append(
            (
                f"resend of an acknowledged line ({trigger})",
                lambda t=trigger, i=i: session.desync(t, i),
            )
        )
        out.append((f"press after {trigger}", lambda i=i: session.press(i + 4)))
    out += [
        ("busy forever (M600): a timeout, not a hang", session.busy_forever),
        ("M876 ends the pause; press again", lambda: (p.send("M876 S0"), session.press(6))),
        ("fatal error (trigger_fatal_error_marlin)", session.fatal),
    ]
    return out


def run_step(fn: Callable[[], object]) -> tuple[str, str]:
    """('ok' | 'FAILED' | 'HUNG', detail), running ``fn`` in a thread with a time limit."""
    result: dict[str, object] = {}

    def target() -> None:
        try:
            result["value"] = fn()
        except Exception as e:  # noqa: BLE001 - every failure is reported
            result["error"] = e

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(STEP_TIMEOUT_S)
    if thread.is_alive():
        return "HUNG", f"still running after {STEP_TIMEOUT_S:g} s"
    if "error" in result:
        e = result["error"]
        return "FAILED", f"{type(e).__name__}: {e}"
    value = result.get("value")
    return "ok", value if isinstance(value, str) else ""


def make_printer(port: str) -> MarlinPrinter:
    kwargs = {"envelope": ENVELOPE, "timeout_s": TIMEOUT_S, "banner_timeout_s": 3.0}
    kwargs |= {"home_timeout_s": 30.0, "busy_timeout_s": BUSY_TIMEOUT_S}
    accepted = inspect.signature(MarlinPrinter).parameters  # older drivers, for comparison
    return MarlinPrinter(port, **{k: v for k, v in kwargs.items() if k in accepted})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--octoprint-python",
        default=os.environ.get(ENV_VAR) or (str(SETUP_VENV) if SETUP_VENV.is_file() else None),
    )
    parser.add_argument("--presses", type=int, default=10, help="clean presses before the faults")
    parser.add_argument("--json", action="store_true", help="print a JSON summary at the end")
    args = parser.parse_args(argv)
    if not args.octoprint_python:
        print(
            f"no OctoPrint: run scripts/setup.sh --dev (makes {SETUP_VENV}), or set {ENV_VAR} "
            "or --octoprint-python to a python with OctoPrint installed",
            file=sys.stderr,
        )
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        peer = Peer(args.octoprint_python, Path(tmp) / "received.txt")
        printer = make_printer(peer.port)
        print(f"OctoPrint {peer.version} virtual printer on {peer.port}; {cpu_summary()}")
        results = []
        try:
            session = Session(peer, printer)
            results = run_steps(steps(session, args.presses), session.reconnect)
        finally:
            printer.close()
            peer.close()
    ok = sum(1 for status, _ in results if status == "ok")
    print(f"{ok}/{len(results)} steps ok")
    counters = {k: getattr(printer, k, "n/a") for k in ("resend_count", "resyncs", "extra_oks")}
    print("driver: " + ", ".join(f"{k} {v}" for k, v in counters.items()))
    if args.json:
        print(json.dumps({"steps": len(results), "ok": ok, "results": results}))
    return 0 if ok == len(results) else 1


def run_steps(
    step_list: list[tuple[str, Callable[[], object]]], recover: Callable[[], object]
) -> list[tuple[str, str]]:
    """Run the steps; after a failed one, reconnect and home (as an operator would), so
    that each fault is tried on its own."""
    results: list[tuple[str, str]] = []
    for number, (name, fn) in enumerate(step_list, 1):
        if results and results[-1][0] == "HUNG":
            status, detail = "NOT RUN", "an earlier step hung"
        else:
            status, detail = run_step(fn)
        results.append((status, detail))
        print(f"step {number:2d} {name}: {status}{': ' + detail if detail else ''}", flush=True)
        if status == "FAILED" and number > 1:
            outcome, why = run_step(recover)
            print(
                f"        reconnected and homed: {outcome}{': ' + why if why else ''}", flush=True
            )
    return results


if __name__ == "__main__":
    sys.exit(main())
