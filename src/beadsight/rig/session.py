"""One collection session on the main thread: the printer driven through the plan, with checks.

A :class:`PressSession` homes the printer, tares the scale and runs each press like the
reference (reference-facts section 5): travel at the clear height (F700), descend
(F200), dwell (G4 P1000), rise (F700), settle. Below ``check_below_z_mm`` the descent
goes in ``descend_step_mm`` steps and the dwell in short slices, so the force is checked
between them (near the limit, with a reading taken after the step ended): above the
limit the press is aborted and the finger lifted at once (:class:`ForceSafety`). A
scale that goes silent stops the session (the check would be blind), and so does a
failure of the :class:`~beadsight.rig.capture.CaptureRecorder`. Every printer command is
logged into the recording with the press it belongs to (``press = -1`` for homing and
parking), and every press event (``press_start``, ``press_end``, ``press_abort``...).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from tqdm import tqdm

from beadsight.config import ConfigError
from beadsight.data.recording import RecordingWriter
from beadsight.devices.base import DeviceError, Printer, Scale
from beadsight.rig.capture import CaptureRecorder
from beadsight.rig.config import FORCE_LIMIT_N, ON_FORCE_LIMIT, SCALE_TIMEOUT_S
from beadsight.rig.plan import PressPlan, PressTarget

logger = logging.getLogger(__name__)

DWELL_SLICE_MS = 200.0  # the dwell is split into slices this long to check the force
FRESH_FORCE_FRACTION = 0.5  # above this fraction of the limit, each step waits for a new reading

T = TypeVar("T")


@dataclass(frozen=True)
class ForceSafety:
    """What protects the sensor during a press.

    force_limit_n: above this force (N) a press is aborted and the finger lifted.
    on_force_limit: "stop" the session then, or "skip" to the next press.
    scale_timeout_s: a scale silent for longer stops the session (the check would be blind).
    """

    force_limit_n: float = FORCE_LIMIT_N
    on_force_limit: str = "stop"
    scale_timeout_s: float = SCALE_TIMEOUT_S

    def __post_init__(self) -> None:
        if self.on_force_limit not in ON_FORCE_LIMIT:
            raise ConfigError(
                f"on_force_limit must be 'stop' or 'skip', got {self.on_force_limit!r}"
            )
        if not self.force_limit_n > 0:
            raise ConfigError(f"force_limit_n must be > 0, got {self.force_limit_n}")
        if not self.scale_timeout_s > 0:
            raise ConfigError(f"scale_timeout_s must be > 0, got {self.scale_timeout_s}")


class SessionStop(Exception):
    """The session must stop: ``status`` (one of collect's STATUS_EXIT) and a message."""

    def __init__(self, status: str, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


class ForceLimitReached(Exception):
    """The force passed the limit during a press (the press is aborted)."""

    def __init__(self, force_n: float):
        super().__init__(f"{force_n:.1f} N")
        self.force_n = force_n


@dataclass(eq=False)
class PressSession:
    """State of one collection run on the main thread (see the module docstring).

    stop_event: set it (from any thread) to stop like Ctrl-C.
    """

    printer: Printer
    scale: Scale
    writer: RecordingWriter
    recorder: CaptureRecorder
    plan: PressPlan
    safety: ForceSafety
    stop_event: threading.Event | None = None
    press: int = -1  # the press the printer commands belong to (-1: homing, parking)
    aborted: list[int] = field(default_factory=list)
    peak_n: float = 0.0  # highest force of the current press, N
    finger_may_be_down: bool = False  # between a press's start and its lift
    bar: tqdm | None = None

    def __post_init__(self) -> None:
        self._log_pos = len(getattr(self.printer, "command_log", []))

    def run_plan(
        self, remaining: Iterable[PressTarget], done: set[int], total: int, progress: bool
    ) -> None:
        """Prepare, run every remaining press (adding each to ``done``, aborted ones too:
        a resume skips them), then park the finger at the clear height."""
        self.prepare()
        self.bar = tqdm(
            total=total, initial=len(done), unit="press", desc="collect", disable=not progress
        )
        for target in remaining:
            self.finger_may_be_down = True
            result = self.do_press(target)
            self.finger_may_be_down = False
            self.bar.update(1)
            done.add(target.index)
            logger.debug("press %d: %s", target.index, result)
        self.finger_may_be_down = True
        self.press = -1
        self.lift()
        self.finger_may_be_down = False

    # --- checks between printer commands -----------------------------------------------------
    def force_now(self, fresh_after: float | None = None) -> float:
        """The newest scale force (N); SessionStop if the scale failed or went silent (the force
        limit would be blind).

        fresh_after: a ``time.monotonic()`` instant; once the force is above
        ``FRESH_FORCE_FRACTION`` of the limit, wait for a reading taken after it, so the
        check sees the depth just reached rather than one a sample period ago.
        """
        try:
            reading = self.scale.latest()
            near_limit = (
                reading is not None
                and reading.force_n > FRESH_FORCE_FRACTION * self.safety.force_limit_n
            )
            if fresh_after is not None and near_limit and hasattr(self.scale, "wait_for_reading"):
                reading = self.scale.wait_for_reading(
                    self.safety.scale_timeout_s, after_mono=fresh_after
                )
        except DeviceError as e:
            raise SessionStop("scale_error", f"scale failed: {e}; finger lifted") from None
        if reading is None or time.monotonic() - reading.t_mono > self.safety.scale_timeout_s:
            age = (
                "no reading"
                if reading is None
                else f"last reading {time.monotonic() - reading.t_mono:.1f} s old"
            )
            raise SessionStop("scale_error", f"scale stopped streaming ({age}); finger lifted")
        return float(reading.force_n)

    def check(self, fresh_after: float | None = None) -> None:
        """Raise SessionStop if the session must end, ForceLimitReached if the force is too high."""
        if self.recorder.failure is not None:
            raise SessionStop(*self.recorder.failure)
        if self.stop_event is not None and self.stop_event.is_set():
            raise KeyboardInterrupt
        force = self.force_now(fresh_after)
        self.peak_n = max(self.peak_n, force)
        if self.bar is not None:
            self.bar.set_postfix_str(f"force {force:5.1f} N", refresh=False)
        if force > self.safety.force_limit_n:
            raise ForceLimitReached(force)

    # --- printer commands, logged with the press they belong to ------------------------------------
    def log_commands(self) -> None:
        log = getattr(self.printer, "command_log", None)
        if log is None:
            return
        new = log[self._log_pos :]
        self._log_pos += len(new)
        for record in new:
            self.writer.write_command(record, press=self.press)

    def run(self, command: Callable[..., T], *args: Any) -> T:
        """Call a printer method, then log the commands it sent (even when it failed)."""
        try:
            return command(*args)
        finally:
            self.log_commands()

    def move(self, x: float | None, y: float | None, z: float | None, feed: float) -> None:
        self.run(self.printer.move, x, y, z, feed)

    def lift(self) -> None:
        """Raise the finger to the clear height (vertical), waiting for it."""
        self.run(self.printer.move, None, None, self.plan.z_clear_mm, self.plan.travel_feed_mm_min)
        self.run(self.printer.wait_for_motion)

    # --- the steps ------------------------------------------------------------------------
    def prepare(self) -> None:
        """Home, heaters off, rise to the clear height, go over the centre, tare."""
        self.press = -1
        position = self.run(self.printer.home)
        self.writer.log_event("homed", position_mm=list(position))
        self.run(self.printer.heaters_off)
        fast = self.plan.position_feed_mm_min
        self.move(None, None, self.plan.z_clear_mm, fast)
        cx, cy = self.plan.centre_xy_mm
        self.move(cx, cy, self.plan.z_clear_mm, fast)
        self.run(self.printer.wait_for_motion)
        self.scale.tare()
        self.writer.log_event("tare")

    def do_press(self, target: PressTarget) -> str:
        """Run one press; returns "ok" or "aborted" (force limit)."""
        plan = self.plan
        self.press = target.index
        self.peak_n = 0.0
        dx, dy = target.x_mm - plan.centre_xy_mm[0], target.y_mm - plan.centre_xy_mm[1]
        self.writer.log_event(
            "press_start",
            press=target.index,
            kind=target.kind,
            x_mm=target.x_mm,
            y_mm=target.y_mm,
            z_mm=target.z_mm,
            offset_mm=[dx, dy],
        )
        try:
            self.check()
            self.move(target.x_mm, target.y_mm, plan.z_clear_mm, plan.travel_feed_mm_min)
            self.run(self.printer.wait_for_motion)
            self.check()
            self.descend(target.z_mm)
            self.dwell(plan.dwell_ms)
        except ForceLimitReached as e:
            self.abort_press(target, e.force_n)
            return "aborted"
        self.lift()
        if plan.settle_ms > 0:
            self.run(self.printer.dwell, plan.settle_ms)
        self.writer.log_event("press_end", press=target.index, peak_force_n=self.peak_n)
        return "ok"

    def descend(self, z_target: float) -> None:
        plan = self.plan
        start = plan.step_start_z_mm
        if start > z_target:
            self.move(None, None, start, plan.press_feed_mm_min)
            self.run(self.printer.wait_for_motion)
            self.check()
        z = max(start, z_target)
        while z > z_target + 1e-9:
            z = max(z_target, z - plan.descend_step_mm)
            self.move(None, None, round(z, 4), plan.press_feed_mm_min)
            self.run(self.printer.wait_for_motion)
            self.check(fresh_after=time.monotonic())

    def dwell(self, ms: float) -> None:
        remaining = ms
        while remaining > 1e-6:
            piece = min(DWELL_SLICE_MS, remaining)
            self.run(self.printer.dwell, piece)
            remaining -= piece
            self.check()

    def abort_press(self, target: PressTarget, force_n: float) -> None:
        logger.warning(
            "press %d: force %.1f N above the limit %.1f N; lifting the finger",
            target.index,
            force_n,
            self.safety.force_limit_n,
        )
        self.lift()
        self.aborted.append(target.index)
        self.writer.log_event(
            "press_abort", press=target.index, force_n=force_n, limit_n=self.safety.force_limit_n
        )
        if self.safety.on_force_limit == "stop":
            raise SessionStop(
                "force_limit",
                f"press {target.index} aborted: force {force_n:.1f} N exceeded the limit "
                f"{self.safety.force_limit_n:g} N; finger lifted and session stopped (check the rig, "
                "then --resume)",
            )
