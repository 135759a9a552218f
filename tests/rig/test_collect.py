"""Collection on the virtual rig: plans, safety, clean stops, resume, the CLI end to end."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import beadsight_ok

from beadsight.cli import main
from beadsight.config import ConfigError
from beadsight.data.dataset import open_dataset
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.run import process_recording
from beadsight.data.recording import open_recording, read_events, read_session
from beadsight.rig.collect import (
    DeviceSpec,
    PressPlan,
    VirtualRigSpec,
    collect,
    open_devices,
    simulator_config,
)

TIME_SCALE = 8.0  # simulated seconds per host second: a 10 s press takes ~1.3 s
CAMERA_FPS = 8.0  # simulated; 64 host frames/s keeps the busy test machine up
IMAGE = 32  # sensor-space frames of the virtual camera


def _plan(rig_config, **kw) -> PressPlan:
    kw.setdefault("calibration_presses", 1)
    kw.setdefault("presses", 1)
    kw.setdefault("settle_ms", 200.0)
    return PressPlan.for_simulator(rig_config, **kw)


class Rig:
    """A virtual rig with connected drivers, through the same open_devices as hardware."""

    def __init__(self, image: int = IMAGE, camera=None, **rig_kw):
        from beadsight.devices.virtual.rig import VirtualRig

        self.spec = VirtualRigSpec(
            time_scale=TIME_SCALE, camera_mode="sensor", image_size_px=image, camera_fps=CAMERA_FPS
        )
        self.config = simulator_config(self.spec)
        self.rig = VirtualRig(
            self.config,
            0,
            time_scale=TIME_SCALE,
            camera_mode="sensor",
            camera_fps=CAMERA_FPS,
            **rig_kw,
        )
        self.own_camera = camera  # replaces the rig's camera (e.g. an OpenCVCamera)

    def __enter__(self):
        self.rig.start()
        spec = DeviceSpec(
            self.rig.printer_port, self.rig.scale_port, "virtual", scale_protocol="beadsight"
        )
        camera = self.own_camera if self.own_camera is not None else self.rig.camera
        self._devices = open_devices(spec, self.rig.envelope, camera=camera)
        self.printer, self.scale, self.camera = self._devices.__enter__()
        return self

    def __exit__(self, *exc):
        self._devices.__exit__(*exc)
        self.rig.close()

    def collect(self, plan, out, **kw):
        kw.setdefault("progress", False)
        kw.setdefault("chunk_frames", 16)
        return collect(
            self.printer,
            self.scale,
            self.camera,
            plan,
            out,
            metadata={"virtual": True, "time_scale": TIME_SCALE},
            **kw,
        )


def when_event(out: Path, predicate, action, timeout_s: float = 60.0) -> threading.Thread:
    """Run ``action()`` once the recording's events satisfy ``predicate(events)``."""

    def watch():
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if (out / "events.jsonl").exists() and predicate(read_events(out)):
                action()
                return
            time.sleep(0.02)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def started(press: int):
    return lambda events: any(
        e["event"] == "press_start" and e.get("press") == press for e in events
    )


def ended(press: int):
    return lambda events: any(e["event"] == "press_end" and e.get("press") == press for e in events)


def _events(out, name):
    return [e for e in read_events(out) if e["event"] == name]


# --- plans --------------------------------------------------------------------------------------
def test_plan_is_seeded_and_within_ranges():
    plan = PressPlan(presses=50, seed=3, calibration_presses=2)
    targets = plan.targets()
    assert (
        len(targets) == 52
        and targets == PressPlan(presses=50, seed=3, calibration_presses=2).targets()
    )
    assert targets != PressPlan(presses=50, seed=4, calibration_presses=2).targets()
    assert [t.kind for t in targets[:3]] == ["calibration", "calibration", "press"]
    assert (targets[0].x_mm, targets[0].y_mm) == (151.8, 108.9)
    xy = np.array([(t.x_mm - 151.8, t.y_mm - 108.9) for t in targets[2:]])
    z = np.array([t.z_mm for t in targets[2:]])
    assert np.abs(xy).max() <= 13.75 and np.abs(xy).max() > 10
    assert z.min() >= 127.0 and z.max() <= 128.0
    assert [t.index for t in targets] == list(range(52))


def test_grid_plan_and_toml(tmp_path):
    grid = PressPlan(presses=9, pattern="grid", calibration_presses=0).targets()
    xs = sorted({round(t.x_mm - 151.8, 6) for t in grid})
    assert xs == [-13.75, 0.0, 13.75]
    path = tmp_path / "plan.toml"
    path.write_text('[plan]\npresses = 7\npattern = "grid"\nz_press_mm = [127.2, 127.4]\n')
    plan = PressPlan.from_toml(path, seed=5)
    assert (plan.presses, plan.pattern, plan.seed, plan.z_press_mm) == (
        7,
        "grid",
        5,
        (127.2, 127.4),
    )
    path.write_text("presses = 3\ndepth = 2\n")
    with pytest.raises(ConfigError, match=r"plan\.toml: unknown plan field\(s\) \['depth'\]"):
        PressPlan.from_toml(path)
    with pytest.raises(ConfigError, match="z_press_mm"):
        PressPlan(z_press_mm=(128.0, 127.0))
    with pytest.raises(ConfigError, match="pattern"):
        PressPlan(pattern="spiral")


def test_plan_outside_the_envelope_is_refused_before_anything_moves(tmp_path):
    from beadsight.devices import MarlinPrinter, SafetyEnvelope

    printer = MarlinPrinter("/dev/null-printer", envelope=SafetyEnvelope())  # never connected
    plan = PressPlan(presses=5, range_mm=20.0, calibration_presses=0, seed=1)
    with pytest.raises(ConfigError, match=r"press plan, press \d+: refused move"):
        collect(printer, None, None, plan, tmp_path / "raw", progress=False)
    assert not (tmp_path / "raw").exists()


# --- sessions on the virtual rig -----------------------------------------------------------------
def test_collect_then_process(tmp_path):
    out = tmp_path / "raw"
    with Rig() as r:
        plan = _plan(r.config)  # a calibration press and a planned one: both kinds of target
        result = r.collect(plan, out)
    assert result.status == "complete" and result.presses_done == 2 and result.frames > 0
    assert [e["press"] for e in _events(out, "press_end")] == [0, 1]
    rec = open_recording(out)
    assert rec.metadata["status"] == "complete" and rec.metadata["plan"]["presses"] == 1
    assert rec.has_monotonic and rec.frame_hw == (IMAGE, IMAGE)
    data_moves = rec.moves.press[rec.moves.is_data]
    assert set(data_moves.tolist()) == {0, 1}
    assert rec.moves.gcode[0] == "G28" and not rec.moves.is_data[0]
    qa = process_recording(
        out, tmp_path / "d.h5", ProcessConfig(image_size=IMAGE, preprocess="none"), progress=False
    )
    assert qa["presses"] == 2
    with open_dataset(tmp_path / "d.h5") as ds:
        assert ds.force_n[ds.valid].max() > 3.0
        targets = plan.targets()
        for (a, b), t in zip(ds.presses, targets, strict=True):
            np.testing.assert_allclose(
                ds.position_mm[a:b].mean(0), (t.x_mm - 151.8, t.y_mm - 108.9), atol=1e-6
            )


def test_deep_press_is_aborted_and_finger_lifted(tmp_path):
    out = tmp_path / "raw"
    with Rig() as r:
        # 3 mm into the pouch: ~55 N, far above a 25 N limit
        plan = _plan(r.config, calibration_presses=0, presses=2, z_press_mm=(126.0, 126.0))
        result = r.collect(plan, out, force_limit_n=25.0)
        finger_z = r.rig.finger_position_mm[2]
        assert r.printer.target[2] == plan.z_clear_mm
    assert result.status == "force_limit" and result.aborted == [0]
    assert "press 0 aborted" in result.message and "25 N" in result.message
    assert finger_z >= plan.z_clear_mm - 1e-6
    abort = _events(out, "press_abort")[0]
    # caught within a step or two of crossing the limit (~6 N per 0.25 mm step here),
    # well before the full 3 mm depth (~55 N)
    assert abort["press"] == 0 and 25.0 < abort["force_n"] < 45.0
    assert not _events(out, "press_end")
    assert read_session(out)["status"] == "force_limit"
    assert len(open_recording(out).frames) == result.frames


def test_injected_force_skips_presses(tmp_path):
    out = tmp_path / "raw"
    with Rig() as r:
        plan = _plan(r.config, presses=1)
        true_force = r.rig.scale_device.force_fn

        def inject():  # a load appears on the scale during press 1
            r.rig.scale_device.force_fn = lambda t: 45.0

        when_event(out, started(1), inject)
        result = r.collect(plan, out, on_force_limit="skip")
        r.rig.scale_device.force_fn = true_force
    assert result.status == "complete" and result.aborted == [1]
    assert [e["press"] for e in _events(out, "press_end")] == [0]
    assert _events(out, "press_abort")[0]["force_n"] > 40.0


def test_resume_continues_the_plan(tmp_path):
    out = tmp_path / "raw"
    stop = threading.Event()
    with Rig() as r:
        plan = _plan(r.config, presses=2)
        when_event(out, ended(0), stop.set)
        first = r.collect(plan, out, stop_event=stop)
        assert first.status == "interrupted"
        done = {e["press"] for e in _events(out, "press_end")}
        assert 0 in done and len(done) < 3
        other_plan = _plan(r.config, presses=9, seed=99)  # ignored: the saved plan continues
        second = r.collect(other_plan, out, resume=True)
    assert second.status == "complete" and second.presses_done == 3
    ends = [e["press"] for e in _events(out, "press_end")]
    assert sorted(ends) == [0, 1, 2] and len(ends) == 3  # no press recorded twice
    rec = open_recording(out)
    assert [s["status"] for s in rec.metadata["sessions"]] == ["interrupted", "complete"]
    assert np.all(np.diff(rec.frames.t_mono) > 0)
    assert (np.diff(rec.frames.chunk) >= 0).all()
    qa = process_recording(
        out, tmp_path / "d.h5", ProcessConfig(image_size=IMAGE, preprocess="none"), progress=False
    )
    assert qa["presses"] == 3


def test_collection_and_live_read_the_same_virtual_camera(tmp_path):
    from helpers.live import BACKEND, tiny_model

    from beadsight.devices import Camera
    from beadsight.devices.virtual import VirtualCamera
    from beadsight.live.sensor import LiveSensor

    with Rig(image=64) as r:
        result = r.collect(_plan(r.config, calibration_presses=0), tmp_path / "raw")
        assert result.ok and result.frames > 0
        camera = r.camera
        assert type(camera) is VirtualCamera and isinstance(camera, Camera)
        readings = []
        with LiveSensor(tiny_model(), camera, **BACKEND) as sensor:
            assert sensor.source is camera
            for reading in sensor.readings():
                readings.append(reading)
                if len(readings) == 3:
                    break
    assert sensor.error is None and len(readings) == 3
    assert readings[0].timestamp_s > open_recording(tmp_path / "raw").frames.t_unix[-1]


def test_collection_records_every_frame_of_a_video_file_camera(tmp_path):
    """The hardware path with OpenCV's camera class: here on a real MJPG file it loops."""
    import cv2

    from beadsight.devices import OpenCVCamera

    video = tmp_path / "grey.avi"
    levels = [20 + 20 * k for k in range(10)]  # frame k of the file is flat grey levels[k]
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (IMAGE, IMAGE))
    for level in levels:
        writer.write(np.full((IMAGE, IMAGE, 3), level, np.uint8))
    writer.release()
    camera = OpenCVCamera(video, width=None, height=None, loop=True)
    with Rig(camera=camera) as r:
        result = r.collect(_plan(r.config, calibration_presses=0), tmp_path / "raw")
    assert result.ok and result.frames > len(levels)  # more than one pass of the file
    rec = open_recording(tmp_path / "raw")
    assert rec.metadata["devices"]["camera"]["type"] == "OpenCVCamera"
    np.testing.assert_array_equal(rec.frames.camera_index, np.arange(result.frames))
    cap = cv2.VideoCapture(str(rec.videos[0]))
    recorded = []
    while len(recorded) < 25:
        ok, image = cap.read()
        if not ok:
            break
        recorded.append(float(image.mean()))
    cap.release()
    expected = [levels[k % len(levels)] for k in range(len(recorded))]
    assert len(recorded) == min(25, int((rec.frames.chunk == 0).sum()))
    np.testing.assert_allclose(recorded, expected, atol=3.0)


def test_camera_unplugged_stops_cleanly(tmp_path):
    out = tmp_path / "raw"
    with Rig() as r:
        when_event(out, started(1), r.camera.unplug)
        result = r.collect(_plan(r.config, presses=3), out)
        assert r.printer.target[2] == r.config.clear_z_mm  # finger lifted
    assert result.status == "camera_disconnected"
    assert "camera disconnected" in result.message
    assert read_session(out)["status"] == "camera_disconnected"
    qa = process_recording(
        out, tmp_path / "d.h5", ProcessConfig(image_size=IMAGE, preprocess="none"), progress=False
    )
    assert qa["frames_written"] == result.frames > 0


def test_printer_error_sends_emergency_stop(tmp_path):
    out = tmp_path / "raw"
    with Rig() as r:
        when_event(out, started(1), lambda: r.rig.printer_device.fail_next())
        result = r.collect(_plan(r.config, presses=2), out)
        assert r.printer.halted
    assert result.status == "printer_error"
    assert "M112" in result.message and "MINTEMP" in result.message
    assert open_recording(out).moves.gcode[-1] == "M112"


def test_silent_scale_stops_and_lifts(tmp_path):
    out = tmp_path / "raw"
    with Rig() as r:
        when_event(out, started(1), r.rig.scale_device.stop_streaming)
        result = r.collect(_plan(r.config, presses=4), out, scale_timeout_s=0.5)
        assert r.printer.target[2] == r.config.clear_z_mm  # finger lifted
        r.rig.scale_device.resume_streaming()
    assert result.status == "scale_error"
    assert "scale stopped streaming" in result.message
    assert read_session(out)["status"] == "scale_error"


# --- through the CLI ------------------------------------------------------------------------------
CLI = [
    sys.executable,
    "-m",
    "beadsight",
    "collect",
    "--virtual",
    "--virtual-camera",
    "sensor",
    "--image-size",
    str(IMAGE),
    "--time-scale",
    str(TIME_SCALE),
    "--calibration-presses",
    "0",
    "--no-progress",
]


def test_cli_ctrl_c_stops_cleanly(tmp_path):
    out = tmp_path / "raw"
    proc = subprocess.Popen(
        [*CLI, "--presses", "20", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (
            (out / "events.jsonl").exists() and started(0)(read_events(out))
        ):
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr[-2000:]
    assert "interrupted" in stdout
    assert read_session(out)["status"] == "interrupted"
    rec = open_recording(out)
    assert len(rec.frames) > 0 and not any("truncated" in w for w in rec.warnings)
    assert rec.moves.xyz_mm[-1, 2] == pytest.approx(137.5)  # the last command lifted the finger


def test_cli_disk_full_keeps_recorded_data(tmp_path):
    """RLIMIT_FSIZE (per file) stands in for a full disk: the video chunk outgrows it."""
    out = tmp_path / "raw"
    # 256 px sensor frames (~25 kB of MJPG each) fill 400 kB in ~16 frames, at a fraction of
    # the raw camera's cost; the plan is longer than the run that the limit cuts short.
    argv = [*CLI[3:], "--presses", "20", "--image-size", "256", "--chunk-frames", "1000"]
    argv += ["--out", str(out)]
    script = textwrap.dedent(f"""
        import resource, signal, sys
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))
        from beadsight.cli import main
        sys.exit(main({argv!r}))
    """)
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 1, res.stdout + res.stderr[-2000:]
    assert "write_error" in res.stdout
    assert "file size limit reached" in res.stdout or "disk full" in res.stdout
    assert read_session(out)["status"] == "write_error"
    # the frames written before the disk refused more are kept and processable
    config = ProcessConfig(image_size=IMAGE, preprocess="none")
    qa = process_recording(out, tmp_path / "d.h5", config, progress=False)
    assert qa["frames_written"] >= 3


def test_cli_collect_argument_errors(tmp_path, capsys):
    assert main(["collect", "--out", str(tmp_path / "x"), "--printer", "/dev/null"]) == 1
    assert "missing --scale, --camera" in capsys.readouterr().err
    assert main(["collect", "--virtual", "--camera", "0", "--out", str(tmp_path / "y")]) == 1
    assert "--virtual replaces" in capsys.readouterr().err


@pytest.mark.slow
def test_end_to_end_collect_process_train_evaluate(tmp_path):
    """collect --virtual -> process -> train -> evaluate, all through the real CLI (in this
    process: the child-process side of the CLI is tested by the Ctrl-C and disk-full tests)."""
    raw, data, runs = tmp_path / "raw", tmp_path / "d.h5", tmp_path / "runs"
    # 2x real time (60 fps of host time) and 3-frame windows: the one training press must keep
    # a window of consecutive frames that ends in contact. At 8x a loaded 2-core machine dropped
    # so many frames that none did; at 3x with 5-frame windows it happened once in ~20 runs.
    beadsight_ok(
        *CLI[3:], "--presses", "3", "--image-size", "64", "--time-scale", "2", "--out", raw
    )
    beadsight_ok(
        "process", raw, "--out", data, "--preprocess", "none", "--image-size", "64", "--no-progress"
    )
    with open_dataset(data) as ds:
        assert ds.num_presses == 3
    beadsight_ok(
        *("train", "--data", data, "--out", runs, "--steps", "2", "--width", "8"),
        *("--batch-size", "4", "--frames", "3", "--threads", "1", "--no-progress"),
        *("--val-stride", "8"),  # validation runs, on every 8th window: the claim is the chain
    )
    checkpoints = sorted(runs.rglob("*.pt"))
    assert checkpoints, f"no checkpoint under {runs}"
    best = next((p for p in checkpoints if p.name == "best.pt"), checkpoints[-1])
    out = beadsight_ok(
        *("evaluate", "--checkpoint", best, "--data", data, "--split", "all"),
        *("--out", tmp_path / "eval", "--no-plots", "--max-frames", "16"),
    )
    metrics = json.loads(next((tmp_path / "eval").rglob("metrics.json")).read_text())
    assert "mae_kpa" in metrics, out
