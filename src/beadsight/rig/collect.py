"""Data collection: a press plan executed on the rig while everything is recorded.

:func:`collect` takes device objects typed by the :mod:`beadsight.devices` protocols (a
:class:`~beadsight.devices.Printer`, a :class:`~beadsight.devices.Scale`, a
:class:`~beadsight.devices.Camera`: the real drivers or the virtual rig's) and a
:class:`~beadsight.rig.plan.PressPlan`, and writes a raw recording
(:class:`beadsight.data.recording.RecordingWriter`) incrementally:

* a :class:`~beadsight.rig.capture.CaptureRecorder` thread takes every camera frame and every
  scale reading as they come;
* the main thread drives the printer through the plan
  (:class:`~beadsight.rig.session.PressSession`), checking the force between steps, and
  logs every executed command and the press events.

Stopping cleanly: Ctrl-C, a camera that disappears, a full disk, a printer error -- in
every case the finger is lifted (or, after a printer error, the printer halted with
M112), the files are closed, and everything recorded so far stays readable. A session
can be resumed (``resume=True``): the saved plan continues after the last press with a
``press_end`` or ``press_abort`` event.

:func:`collect_with_hardware` and :func:`collect_with_virtual_rig` open the devices for
the command line (:class:`DeviceSpec`, :class:`VirtualRigSpec`) and call :func:`collect`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from beadsight import __version__
from beadsight.config import SensorGeometry
from beadsight.data.recording import RecordingError, RecordingWriter, read_events, read_session
from beadsight.devices.base import Camera, DeviceError, Printer, SafetyError, Scale
from beadsight.devices.envelope import SafetyEnvelope
from beadsight.rig.capture import CaptureRecorder
from beadsight.rig.config import FORCE_LIMIT_N, SCALE_TIMEOUT_S, DeviceSpec, VirtualRigSpec
from beadsight.rig.plan import PATTERNS, PressPlan, PressTarget, check_plan, envelope_for
from beadsight.rig.session import ForceSafety, PressSession, SessionStop

__all__ = [
    "PATTERNS",
    "STATUS_EXIT",
    "CollectResult",
    "DeviceSpec",
    "ForceSafety",
    "PressPlan",
    "PressTarget",
    "VirtualRigSpec",
    "collect",
    "collect_with_hardware",
    "collect_with_virtual_rig",
    "envelope_for",
    "open_devices",
    "simulator_config",
]

logger = logging.getLogger(__name__)

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


def collect(
    printer: Printer,
    scale: Scale,
    camera: Camera,
    plan: PressPlan,
    out: str | Path,
    *,
    resume: bool = False,
    force_limit_n: float = FORCE_LIMIT_N,
    on_force_limit: str = "stop",
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
    safety = ForceSafety(force_limit_n, on_force_limit, scale_timeout_s)
    out = Path(out)
    plan, done = _plan_and_done(out, plan, resume)
    targets = plan.targets()
    remaining = [t for t in targets if t.index not in done]
    if resume and not remaining:
        message = f"all {len(targets)} presses were already recorded; nothing to resume"
        return CollectResult(out, "complete", message, len(targets), len(targets), 0, 0)
    check_plan(printer, plan, targets)
    for device in (printer, scale, camera):
        device.connect()
    meta = _session_metadata(printer, scale, camera, plan, safety, metadata)
    writer = RecordingWriter(
        out,
        meta,
        frame_hw=(camera.height, camera.width),
        fps=camera.fps,
        chunk_frames=chunk_frames,
        resume=resume,
    )
    recorder = CaptureRecorder(writer, camera, scale)
    session = PressSession(printer, scale, writer, recorder, plan, safety, stop_event)
    writer.log_event(
        "session_start", resume=resume, presses_total=len(targets), presses_remaining=len(remaining)
    )
    recorder.start()
    try:
        status, message = _drive(session, remaining, done, len(targets), progress)
    finally:
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


def _plan_and_done(out: Path, plan: PressPlan, resume: bool) -> tuple[PressPlan, set[int]]:
    """The plan to run and the presses already recorded (the saved ones when resuming)."""
    if not resume:
        return plan, set()
    saved = read_session(out)
    if "plan" not in saved:
        raise RecordingError(f"{out}: session.json has no plan to resume")
    done = {
        int(e["press"])
        for e in read_events(out)
        if e.get("event") in ("press_end", "press_abort") and "press" in e
    }
    return PressPlan.from_dict(saved["plan"]), done


def _session_metadata(
    printer: Printer,
    scale: Scale,
    camera: Camera,
    plan: PressPlan,
    safety: ForceSafety,
    extra: dict[str, Any] | None,
) -> dict[str, Any]:
    """session.json's metadata: software, devices, plan, geometry, the force limit."""
    return {
        "software": {"beadsight": __version__},
        "devices": {
            "printer": _device_info(printer, "port", "baudrate"),
            "scale": _device_info(scale, "port", "baudrate", "protocol"),
            "camera": _device_info(camera, "source", "width", "height", "fps"),
        },
        "plan": plan.to_dict(),
        "centre_xy_mm": list(plan.centre_xy_mm),
        "geometry": SensorGeometry(press_range_mm=plan.range_mm).to_dict(),
        "force_limit_n": safety.force_limit_n,
        **(extra or {}),
    }


def _device_info(obj: Any, *names: str) -> dict[str, Any]:
    info = {"type": type(obj).__name__}
    for name in ("name", *names):
        value = getattr(obj, name, None)
        if value is not None:
            info[name] = value if isinstance(value, (int, float, str, bool)) else str(value)
    return info


def _drive(
    session: PressSession, remaining: list[PressTarget], done: set[int], total: int, progress: bool
) -> tuple[str, str]:
    """Run the session's plan; (status, message) for each way it can end. The finger is
    lifted whenever it may be down, except after a printer error (then M112 is sent)."""
    try:
        session.run_plan(remaining, done, total, progress)
        return "complete", f"{total} presses recorded"
    except KeyboardInterrupt:
        return "interrupted", "interrupted (Ctrl-C); finger lifted, recording kept"
    except SessionStop as e:
        return e.status, e.message
    except RecordingError as e:
        return "write_error", str(e)
    except SafetyError as e:
        return "printer_error", f"move refused, nothing sent: {e}"
    except DeviceError as e:
        if e.device != session.printer.name:
            return "scale_error", f"{e}; finger lifted"
        session.finger_may_be_down = False
        _emergency_stop(session.printer)
        session.press = -1
        session.log_commands()
        return "printer_error", f"printer failed: {e}; emergency stop (M112) sent"
    finally:
        if session.bar is not None:
            session.bar.close()
        if session.finger_may_be_down:
            _safe_lift(session)


def _safe_lift(session: PressSession) -> None:
    """Lift the finger after an interruption; if even that fails, halt the printer."""
    try:
        session.press = -1
        session.lift()
    except Exception as e:  # noqa: BLE001 - last resort: make the printer stop
        logger.error("could not lift the finger (%s); sending emergency stop", e)
        _emergency_stop(session.printer)
    try:
        session.log_commands()
    except RecordingError as e:
        logger.error("%s", e)


def _emergency_stop(printer: Printer) -> None:
    try:
        printer.emergency_stop()
    except Exception as e:  # noqa: BLE001
        logger.error("emergency stop failed: %s", e)


def _close_writer(
    writer: RecordingWriter,
    recorder: CaptureRecorder,
    status: str,
    message: str,
    done: set[int],
    session: PressSession,
) -> tuple[str, str]:
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
    spec: DeviceSpec, envelope: SafetyEnvelope | None = None, camera: Camera | None = None
) -> Iterator[tuple[Printer, Scale, Camera]]:
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
