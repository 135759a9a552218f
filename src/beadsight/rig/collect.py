"""Data collection: a press plan executed on the rig while everything is recorded.

:func:`collect` takes device objects (a printer, a scale, a camera: the real drivers or
the virtual rig's, see :mod:`beadsight.devices`) and a :class:`PressPlan`, and writes a
raw recording (:class:`beadsight.data.recording.RecordingWriter`) incrementally:

* a recorder thread takes every camera frame and every scale reading as they come;
* the main thread drives the printer through the plan and logs every executed command
  (with the press it belongs to: ``press = -1`` for homing and parking) and the press
  events (``press_start``, ``press_end``, ``press_abort``, ``error``...).

A press, like the reference (reference-facts section 5): travel at the clear height
(F700), descend (F200), dwell (G4 P1000), rise (F700), settle. Below ``check_below_z_mm``
the descent goes in ``descend_step_mm`` steps and the dwell in short slices, so the
force is checked between them (near the limit, with a reading taken after the step
ended): above ``force_limit_n`` the press is aborted and the finger lifted at once.
A scale that goes silent stops the session (the check would be blind).

Stopping cleanly: Ctrl-C, a camera that disappears, a full disk, a printer error -- in
every case the finger is lifted (or, after a printer error, the printer halted with
M112), the files are closed, and everything recorded so far stays readable. A session
can be resumed (``resume=True``): the saved plan continues after the last press with a
``press_end`` or ``press_abort`` event.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from beadsight import __version__
from beadsight.config import ConfigError, SensorGeometry
from beadsight.data.recording import RecordingError, RecordingWriter, read_events, read_session
from beadsight.devices.base import (
    CameraDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
    SafetyError,
)
from beadsight.rig.config import (
    FORCE_LIMIT_N,
    ON_FORCE_LIMIT,
    SCALE_TIMEOUT_S,
    DeviceSpec,
    VirtualRigSpec,
)
from beadsight.rig.plan import PressPlan, PressTarget

logger = logging.getLogger(__name__)

DWELL_SLICE_MS = 200.0  # the dwell is split into slices this long to check the force
CAMERA_READ_TIMEOUT_S = 0.5  # recorder thread: wait this long for a frame, then check for stop
RECORDER_JOIN_S = 5.0
FRESH_FORCE_FRACTION = 0.5  # above this fraction of the limit, each step waits for a new reading
STATUS_EXIT = (
    "complete",
    "interrupted",
    "force_limit",
    "camera_disconnected",
    "write_error",
    "printer_error",
    "scale_error",
)


@dataclass
class CollectResult:
    """How a session ended. ``status``: one of STATUS_EXIT; ``message``: one line for people."""

    path: Path
    status: str
    message: str
    presses_done: int
    presses_total: int
    frames: int
    readings: int
    aborted: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status == "complete"


class _Stop(Exception):
    """Internal: the session must stop (status, message)."""

    def __init__(self, status: str, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


class _ForceLimit(Exception):
    def __init__(self, force_n: float):
        super().__init__(f"{force_n:.1f} N")
        self.force_n = force_n


# --- recorder thread --------------------------------------------------------------------
class _Recorder:
    """Background thread: every camera frame and scale reading into the writer."""

    def __init__(self, writer: RecordingWriter, camera: Any, scale: Any):
        self.writer = writer
        self.camera = camera
        self.scale = scale
        self.failure: tuple[str, str] | None = None
        self.timeouts = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="beadsight recorder", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=RECORDER_JOIN_S)
        if self._thread.is_alive():
            logger.warning("recorder thread did not stop within %.0f s", RECORDER_JOIN_S)

    def _fail(self, status: str, message: str) -> None:
        if self.failure is None:
            self.failure = (status, message)
            logger.error("%s", message)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._drain_scale()
                try:
                    frame = self.camera.read(timeout_s=CAMERA_READ_TIMEOUT_S)
                except DeviceTimeoutError:
                    self.timeouts += 1
                    continue
                self.writer.write_frame(
                    frame.image, t_unix=frame.t_unix, t_mono=frame.t_mono, camera_index=frame.index
                )
            except CameraDisconnectedError as e:
                self._fail("camera_disconnected", f"camera disconnected: {e}")
                break
            except RecordingError as e:
                self._fail("write_error", str(e))
                break
            except DeviceError as e:
                self._fail("scale_error", f"scale failed: {e}")
                break
            except Exception as e:  # noqa: BLE001 - the main thread reports it
                logger.exception("recorder thread crashed")
                self._fail("write_error", f"recorder failed: {type(e).__name__}: {e}")
                break
        try:
            self._drain_scale()
        except (DeviceError, RecordingError):
            pass

    def _drain_scale(self) -> None:
        readings = self.scale.drain()
        if readings:
            self.writer.write_readings(readings)


# --- the session -------------------------------------------------------------------------
class _Session:
    """State of one collection run (main thread)."""

    def __init__(
        self,
        printer,
        scale,
        writer,
        recorder,
        plan,
        force_limit_n,
        on_force_limit,
        stop_event,
        scale_timeout_s=SCALE_TIMEOUT_S,
    ):
        self.printer = printer
        self.scale = scale
        self.writer = writer
        self.recorder = recorder
        self.plan = plan
        self.force_limit_n = force_limit_n
        self.on_force_limit = on_force_limit
        self.stop_event = stop_event
        self.scale_timeout_s = float(scale_timeout_s)
        self.press = -1
        self._log_pos = len(getattr(printer, "command_log", []))
        self.aborted: list[int] = []
        self.peak_n = 0.0
        self.bar: tqdm | None = None

    # --- checks between printer commands -----------------------------------------------------
    def force_now(self, fresh_after: float | None = None) -> float:
        """The newest scale force (N); _Stop if the scale failed or went silent (the force
        limit would be blind).

        fresh_after: a ``time.monotonic()`` instant; once the force is above
        ``FRESH_FORCE_FRACTION`` of the limit, wait for a reading taken after it, so the
        check sees the depth just reached rather than one a sample period ago.
        """
        try:
            reading = self.scale.latest()
            near_limit = (
                reading is not None and reading.force_n > FRESH_FORCE_FRACTION * self.force_limit_n
            )
            if fresh_after is not None and near_limit and hasattr(self.scale, "wait_for_reading"):
                reading = self.scale.wait_for_reading(self.scale_timeout_s, after_mono=fresh_after)
        except DeviceError as e:
            raise _Stop("scale_error", f"scale failed: {e}; finger lifted") from None
        if reading is None or time.monotonic() - reading.t_mono > self.scale_timeout_s:
            age = (
                "no reading"
                if reading is None
                else f"last reading {time.monotonic() - reading.t_mono:.1f} s old"
            )
            raise _Stop("scale_error", f"scale stopped streaming ({age}); finger lifted")
        return float(reading.force_n)

    def check(self, fresh_after: float | None = None) -> None:
        """Raise _Stop if the session must end, _ForceLimit if the force is too high."""
        if self.recorder.failure is not None:
            raise _Stop(*self.recorder.failure)
        if self.stop_event is not None and self.stop_event.is_set():
            raise KeyboardInterrupt
        force = self.force_now(fresh_after)
        self.peak_n = max(self.peak_n, force)
        if self.bar is not None:
            self.bar.set_postfix_str(f"force {force:5.1f} N", refresh=False)
        if force > self.force_limit_n:
            raise _ForceLimit(force)

    # --- printer commands, logged with the press they belong to ------------------------------------
    def log_commands(self) -> None:
        log = getattr(self.printer, "command_log", None)
        if log is None:
            return
        new = log[self._log_pos :]
        self._log_pos += len(new)
        for record in new:
            self.writer.write_command(record, press=self.press)

    def run(self, method: str, *args: Any) -> Any:
        try:
            return getattr(self.printer, method)(*args)
        finally:
            self.log_commands()

    def move(self, x, y, z, feed):
        self.run("move", x, y, z, feed)

    def lift(self) -> None:
        """Raise the finger to the clear height (vertical), waiting for it."""
        self.run("move", None, None, self.plan.z_clear_mm, self.plan.travel_feed_mm_min)
        self.run("wait_for_motion")

    # --- the steps ------------------------------------------------------------------------
    def prepare(self) -> None:
        """Home, heaters off, rise to the clear height, go over the centre, tare."""
        self.press = -1
        position = self.run("home")
        self.writer.log_event("homed", position_mm=list(position))
        self.run("heaters_off")
        fast = self.plan.position_feed_mm_min
        self.move(None, None, self.plan.z_clear_mm, fast)
        cx, cy = self.plan.centre_xy_mm
        self.move(cx, cy, self.plan.z_clear_mm, fast)
        self.run("wait_for_motion")
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
            self.run("wait_for_motion")
            self.check()
            self.descend(target.z_mm)
            self.dwell(plan.dwell_ms)
        except _ForceLimit as e:
            self.abort_press(target, e.force_n)
            return "aborted"
        self.lift()
        if plan.settle_ms > 0:
            self.run("dwell", plan.settle_ms)
        self.writer.log_event("press_end", press=target.index, peak_force_n=self.peak_n)
        return "ok"

    def descend(self, z_target: float) -> None:
        plan = self.plan
        start = plan.step_start_z_mm
        if start > z_target:
            self.move(None, None, start, plan.press_feed_mm_min)
            self.run("wait_for_motion")
            self.check()
        z = max(start, z_target)
        while z > z_target + 1e-9:
            z = max(z_target, z - plan.descend_step_mm)
            self.move(None, None, round(z, 4), plan.press_feed_mm_min)
            self.run("wait_for_motion")
            self.check(fresh_after=time.monotonic())

    def dwell(self, ms: float) -> None:
        remaining = ms
        while remaining > 1e-6:
            piece = min(DWELL_SLICE_MS, remaining)
            self.run("dwell", piece)
            remaining -= piece
            self.check()

    def abort_press(self, target: PressTarget, force_n: float) -> None:
        logger.warning(
            "press %d: force %.1f N above the limit %.1f N; lifting the finger",
            target.index,
            force_n,
            self.force_limit_n,
        )
        self.lift()
        self.aborted.append(target.index)
        self.writer.log_event(
            "press_abort", press=target.index, force_n=force_n, limit_n=self.force_limit_n
        )
        if self.on_force_limit == "stop":
            raise _Stop(
                "force_limit",
                f"press {target.index} aborted: force {force_n:.1f} N exceeded the limit "
                f"{self.force_limit_n:g} N; finger lifted and session stopped (check the rig, "
                "then --resume)",
            )


def _device_info(obj: Any, *names: str) -> dict[str, Any]:
    info = {"type": type(obj).__name__}
    for name in ("name", *names):
        value = getattr(obj, name, None)
        if value is not None:
            info[name] = value if isinstance(value, (int, float, str, bool)) else str(value)
    return info


def _check_plan(printer: Any, plan: PressPlan, targets: list[PressTarget]) -> None:
    envelope = getattr(printer, "envelope", None)
    if envelope is None:
        return
    name = getattr(printer, "name", "printer")
    for t in targets:
        for z in (plan.z_clear_mm, t.z_mm):
            try:
                envelope.check_point((t.x_mm, t.y_mm, z), device=name)
            except SafetyError as e:
                raise ConfigError(f"press plan, press {t.index}: {e.detail}") from None


def collect(
    printer: Any,
    scale: Any,
    camera: Any,
    plan: PressPlan,
    out: str | Path,
    *,
    resume: bool = False,
    force_limit_n: float = FORCE_LIMIT_N,
    on_force_limit: str = ON_FORCE_LIMIT[0],
    metadata: dict[str, Any] | None = None,
    chunk_frames: int | None = None,
    progress: bool = True,
    stop_event: threading.Event | None = None,
    scale_timeout_s: float = SCALE_TIMEOUT_S,
) -> CollectResult:
    """Run ``plan`` on the devices and record everything into the folder ``out``.

    printer, scale, camera: device objects (:mod:`beadsight.devices`); connected here if
    needed, never closed here. resume: continue the session in ``out`` with its saved plan
    (``plan`` is then ignored). force_limit_n: above this force (N) a press is aborted and
    the finger lifted; on_force_limit: "stop" the session then, or "skip" to the next
    press. stop_event: set it (from any thread) to stop like Ctrl-C. scale_timeout_s: a
    scale silent for longer stops the session (the force limit would be blind).

    Returns a :class:`CollectResult`; it does not raise for the ways a session ends
    (Ctrl-C, force limit, camera lost, disk full, printer error): the recording is
    closed and readable in every case.
    """
    if on_force_limit not in ON_FORCE_LIMIT:
        raise ConfigError(f"on_force_limit must be one of {ON_FORCE_LIMIT}, got {on_force_limit!r}")
    if not force_limit_n > 0:
        raise ConfigError(f"force_limit_n must be > 0, got {force_limit_n}")
    out = Path(out)
    done: set[int] = set()
    if resume:
        saved = read_session(out)
        if "plan" not in saved:
            raise RecordingError(f"{out}: session.json has no plan to resume")
        plan = PressPlan.from_dict(saved["plan"])
        done = {
            int(e["press"])
            for e in read_events(out)
            if e.get("event") in ("press_end", "press_abort") and "press" in e
        }
    targets = plan.targets()
    remaining = [t for t in targets if t.index not in done]
    if resume and not remaining:
        return CollectResult(
            out,
            "complete",
            f"all {len(targets)} presses were already recorded; nothing to resume",
            len(targets),
            len(targets),
            0,
            0,
        )
    _check_plan(printer, plan, targets)
    for device in (printer, scale, camera):
        device.connect()
    meta = {
        "software": {"beadsight": __version__},
        "devices": {
            "printer": _device_info(printer, "port", "baudrate"),
            "scale": _device_info(scale, "port", "baudrate", "protocol"),
            "camera": _device_info(camera, "source", "width", "height", "fps"),
        },
        "plan": plan.to_dict(),
        "centre_xy_mm": list(plan.centre_xy_mm),
        "geometry": SensorGeometry(press_range_mm=plan.range_mm).to_dict(),
        "force_limit_n": force_limit_n,
        **(metadata or {}),
    }
    writer = RecordingWriter(
        out,
        meta,
        frame_hw=(camera.height, camera.width),
        fps=camera.fps,
        chunk_frames=chunk_frames,
        resume=resume,
    )
    recorder = _Recorder(writer, camera, scale)
    session = _Session(
        printer,
        scale,
        writer,
        recorder,
        plan,
        force_limit_n,
        on_force_limit,
        stop_event,
        scale_timeout_s,
    )
    writer.log_event(
        "session_start", resume=resume, presses_total=len(targets), presses_remaining=len(remaining)
    )
    recorder.start()
    status, message = "complete", f"{len(targets)} presses recorded"
    lift = False
    try:
        session.prepare()
        session.bar = tqdm(
            total=len(targets),
            initial=len(targets) - len(remaining),
            unit="press",
            desc="collect",
            disable=not progress,
        )
        for target in remaining:
            lift = True
            result = session.do_press(target)
            lift = False
            session.bar.update(1)
            done.add(target.index)  # aborted presses count as done: resume skips them
            logger.debug("press %d: %s", target.index, result)
        lift = True
        session.press = -1
        session.lift()
        lift = False
    except KeyboardInterrupt:
        status, message = "interrupted", "interrupted (Ctrl-C); finger lifted, recording kept"
    except _Stop as e:
        status, message = e.status, e.message
    except RecordingError as e:
        status, message = "write_error", str(e)
    except SafetyError as e:
        status, message = "printer_error", f"move refused, nothing sent: {e}"
    except DeviceError as e:
        if e.device != getattr(printer, "name", e.device):
            status, message = "scale_error", f"{e}; finger lifted"
        else:
            status, message = "printer_error", f"printer failed: {e}; emergency stop (M112) sent"
            lift = False
            _emergency_stop(printer)
            session.press = -1
            session.log_commands()
    finally:
        if session.bar is not None:
            session.bar.close()
        if lift:
            _safe_lift(session, printer)
        recorder.stop()
        stats = getattr(camera, "stats", None)
        if stats is not None and dataclasses.is_dataclass(stats):
            writer.metadata["camera_stats"] = dataclasses.asdict(stats)
        status, message = _close_writer(writer, recorder, status, message, done, session)
    return CollectResult(
        out,
        status,
        message,
        len(done),
        len(targets),
        writer.frames_written,
        writer.readings_written,
        session.aborted,
    )


def _safe_lift(session: _Session, printer: Any) -> None:
    """Lift the finger after an interruption; if even that fails, halt the printer."""
    try:
        session.press = -1
        session.lift()
    except Exception as e:  # noqa: BLE001 - last resort: make the printer stop
        logger.error("could not lift the finger (%s); sending emergency stop", e)
        _emergency_stop(printer)
    try:
        session.log_commands()
    except RecordingError as e:
        logger.error("%s", e)


def _emergency_stop(printer: Any) -> None:
    try:
        printer.emergency_stop()
    except Exception as e:  # noqa: BLE001
        logger.error("emergency stop failed: %s", e)


def _close_writer(writer, recorder, status, message, done, session) -> tuple[str, str]:
    if recorder.failure is not None and status == "complete":
        status, message = recorder.failure
    try:
        writer.log_event(
            "session_end",
            status=status,
            message=message,
            presses_done=len(done),
            aborted=session.aborted,
        )
    except RecordingError as e:
        logger.error("%s", e)
    try:
        writer.close(status, message=message)
    except RecordingError as e:
        logger.error("%s", e)
        if status == "complete":
            status, message = "write_error", str(e)
    return status, message


# --- devices for the command line ---------------------------------------------------------
@contextlib.contextmanager
def open_devices(
    spec: DeviceSpec, envelope: Any = None, camera: Any = None
) -> Iterator[tuple[Any, Any, Any]]:
    """Printer, scale and camera drivers for ``spec`` (connected; closed on exit).

    ``camera`` replaces the camera of ``spec`` (the virtual rig passes its own).
    """
    from beadsight.devices import HX711Scale, MarlinPrinter, OpenCVCamera

    printer = MarlinPrinter(spec.printer_port, spec.printer_baud, envelope=envelope)
    scale = HX711Scale(spec.scale_port, spec.scale_baud, protocol=spec.scale_protocol)
    if camera is None:
        camera = OpenCVCamera(spec.camera, spec.camera_width, spec.camera_height, spec.camera_fps)
    with contextlib.ExitStack() as stack:
        for device in (printer, scale, camera):
            device.connect()
            stack.callback(device.close)
        yield printer, scale, camera


def envelope_for(plan: PressPlan) -> Any:
    """A safety envelope around the plan's sensor centre: the default margins (floor
    126.5 mm, clear 135 mm, +-15 mm) unless the plan goes beyond them."""
    from beadsight.devices import SafetyEnvelope

    default = SafetyEnvelope(centre_xy_mm=plan.centre_xy_mm)
    return SafetyEnvelope(
        centre_xy_mm=plan.centre_xy_mm,
        xy_half_range_mm=max(default.xy_half_range_mm, plan.range_mm + 1.0),
        z_floor_mm=min(default.z_floor_mm, plan.z_press_mm[0] - 0.5),
        z_clear_mm=min(default.z_clear_mm, plan.z_clear_mm),
    )


def collect_with_hardware(
    spec: DeviceSpec, plan: PressPlan, out: str | Path, **kwargs: Any
) -> CollectResult:
    """Open the real devices of ``spec`` and run :func:`collect`."""
    if kwargs.get("resume"):
        plan = PressPlan.from_dict(read_session(out).get("plan", plan.to_dict()))
    with open_devices(spec, envelope_for(plan)) as (printer, scale, camera):
        return collect(
            printer,
            scale,
            camera,
            plan,
            out,
            metadata={"virtual": False, **kwargs.pop("metadata", {})},
            **kwargs,
        )


def simulator_config(spec: VirtualRigSpec) -> Any:
    from beadsight.sim import SimConfig

    return SimConfig(image_size_px=spec.image_size_px)


def collect_with_virtual_rig(
    spec: VirtualRigSpec, plan: PressPlan, out: str | Path, **kwargs: Any
) -> CollectResult:
    """Build a :class:`~beadsight.devices.virtual.VirtualRig` and run the same path as
    real hardware: drivers on its serial ports, its camera."""
    from beadsight.devices.virtual.rig import VirtualRig

    config = simulator_config(spec)
    with VirtualRig(
        config,
        spec.seed,
        time_scale=spec.time_scale,
        camera_mode=spec.camera_mode,
        camera_fps=spec.camera_fps,
        scale_protocol=spec.scale_protocol,
    ) as rig:
        devices = DeviceSpec(
            rig.printer_port, rig.scale_port, camera="virtual", scale_protocol=spec.scale_protocol
        )
        meta = {
            "virtual": True,
            "time_scale": spec.time_scale,
            "virtual_rig": dataclasses.asdict(spec),
            **kwargs.pop("metadata", {}),
        }
        with open_devices(devices, rig.envelope, camera=rig.camera) as (printer, scale, camera):
            return collect(printer, scale, camera, plan, out, metadata=meta, **kwargs)
