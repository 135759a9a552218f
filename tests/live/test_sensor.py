"""Live sensing: sources -> predictor -> readings, faults, recording, headless CLI."""

from __future__ import annotations

import base64
import json
import math
import time
import urllib.error
import urllib.request
from dataclasses import replace

import cv2
import numpy as np
import pytest
from helpers.live import (
    BACKEND,
    SPAN,
    TINY,
    TORCH,
    ScriptedSource,
    StatusLog,
    live_argv,
    live_sim_args,
    press_frames,
    wait_until,
    write_video,
)

from beadsight.cli import main
from beadsight.devices.clock import SteppedClock
from beadsight.devices.virtual import PlaybackCamera
from beadsight.geometry import centre_of_pressure_mm, total_force_n
from beadsight.live.config import LiveRunConfig
from beadsight.live.outputs.viewer.server import ViewerServer
from beadsight.live.recording.readings import ReadingsFileError, open_readings
from beadsight.live.run import run_live
from beadsight.live.sensor import LiveSensor
from beadsight.live.settings import LiveSettings
from beadsight.live.sources import frame_converter
from beadsight.preprocess import FrameSizeError, Preprocessor

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads


@pytest.fixture(scope="module")
def presses():
    return press_frames(presses=2, per_press=30)


def test_every_reading_matches_the_model_on_its_window(model, presses):
    frames, force = presses
    source = ScriptedSource(frames, forces=force)
    sensor = LiveSensor(model, source, **BACKEND).open()  # the model's own readings
    stream = sensor.updates()  # registered before start: sees every reading
    with sensor:
        updates = list(stream)
        assert sensor.error is None
        assert sensor.status.state == "ended"
    assert len(updates) == len(frames) - SPAN + 1
    expected = model.predict(np.stack([frames[i : i + SPAN] for i in range(len(updates))]))
    for k, u in enumerate(updates):
        r = u.reading
        assert u.source_index == k + SPAN - 1
        assert r.timestamp_s == pytest.approx(source.t0 + u.source_index / source.fps)
        np.testing.assert_allclose(r.pressure_kpa, expected[k], rtol=1e-4, atol=1e-4)
        assert r.force_n == pytest.approx(float(total_force_n(expected[k], TINY)), rel=1e-4)
        np.testing.assert_allclose(r.cop_mm, centre_of_pressure_mm(expected[k], TINY), atol=1e-3)
        assert u.reference_force_n == force[u.source_index]
        np.testing.assert_array_equal(u.frame_rgb, frames[u.source_index])
    stats = sensor.stats()
    assert stats.readings == len(updates) and stats.skipped_frames == 0


def test_paced_source_runs_at_camera_rate_and_reports_latency(model, presses):
    frames, force = presses
    fps = 30.0
    source = PlaybackCamera(lambda: zip(frames, force, strict=True), fps, name="paced")
    got, stats_during = [], []

    def on_reading(reading):
        got.append(reading)
        stats_during.append(sensor.stats())

    sensor = LiveSensor(model, source, **BACKEND)
    sensor.on_reading(on_reading)  # registered before start: sees every reading
    with sensor:
        assert sensor.wait(30)
    assert sensor.status.state == "ended" and "60 frames" in sensor.status.message
    stats = stats_during[-1]
    # every frame the source produced entered the window, or was skipped and counted
    assert stats.frames + stats.skipped_frames >= len(frames) - 1
    assert stats.readings <= stats.frames - SPAN + 1
    assert 0.4 * fps < stats.rate_hz < 1.4 * fps  # busy CI machines: generous
    assert 0 < stats.latency_p50_s <= stats.latency_p99_s < 1.0
    assert 0 < stats.inference_p50_s <= stats.latency_p50_s + 1e-3
    stamps = np.array([r.timestamp_s for r in got])
    assert np.all(np.diff(stamps) > 0)
    assert abs(stamps[0] - time.time()) < 30  # capture clock is unix time


def test_loop_slower_than_camera_keeps_windows_consecutive(model, presses):
    """At 150 fps the camera outruns inference: frames that arrive meanwhile enter the
    window without readings of their own, so each reading still covers T consecutive
    frames (no reset, no stale window). The camera runs on a stepped clock (a frame every
    1/150 s of its time, stamped with that time, about 1000 a second of host time) and its
    queue holds the whole clip, so a loaded machine that stalls the sensing thread changes
    when frames arrive but not which frames or their stamps."""
    frames, force = presses
    source = PlaybackCamera(
        lambda: zip(frames, force, strict=True),
        fps=150,
        name="fast",
        clock=SteppedClock(),
        queue_frames=len(frames),
    )
    updates, stats = [], []

    def on_update(update):
        updates.append(update)
        stats.append(sensor.stats())

    sensor = LiveSensor(model, source, **BACKEND)
    sensor.on_update(on_update)
    with sensor:
        assert sensor.wait(30)
    assert sensor.error is None
    assert stats[-1].rate_hz < stats[-1].source_rate_hz  # it did fall behind
    assert len(updates) < len(frames) - SPAN + 1
    ends = np.array([u.source_index for u in updates])
    windows = np.stack([frames[i - SPAN + 1 : i + 1] for i in ends])
    expected = model.predict(windows)
    for u, want in zip(updates, expected, strict=True):
        np.testing.assert_allclose(u.reading.pressure_kpa, want, rtol=1e-4, atol=1e-4)
    # every frame entered the window, except those more than a window behind (counted)
    assert updates[-1].reading.frame_index + stats[-1].skipped_frames == ends[-1]


def test_readings_iterator_and_callbacks_see_the_same_readings(model, presses):
    frames = presses[0][:30]  # one press: 16 readings
    from_callback = []
    sensor = LiveSensor(model, ScriptedSource(frames), **BACKEND).open()
    remove = sensor.on_reading(from_callback.append)
    readings = sensor.readings()
    with sensor:
        from_iterator = list(readings)
        remove()
    assert [r.frame_index for r in from_iterator] == [r.frame_index for r in from_callback]
    assert len(from_iterator) == len(frames) - SPAN + 1


def test_failing_callback_does_not_stop_sensing(model, presses):
    frames = presses[0][:30]  # one press: 16 readings

    def broken(_reading):
        raise RuntimeError("user bug")

    sensor = LiveSensor(model, ScriptedSource(frames), **BACKEND).open()
    sensor.on_reading(broken)
    readings = sensor.readings()
    with sensor:
        assert len(list(readings)) == len(frames) - SPAN + 1
    assert sensor.error is None


def test_reference_camera_frames_go_through_reference_preprocessing(model):
    rng = np.random.default_rng(1)
    raw = rng.integers(0, 256, size=(SPAN + 1, 1024, 1280, 3), dtype=np.uint8)
    pre = Preprocessor.reference((1024, 1280), TINY.image_size_px)
    sensor = LiveSensor(model, ScriptedSource(raw, channel_order="BGR"), **BACKEND).open()
    stream = sensor.readings()
    with sensor:
        readings = list(stream)
    expected = model.predict(np.stack([pre(f) for f in raw[1:]]))
    assert len(readings) == 2
    np.testing.assert_allclose(readings[-1].pressure_kpa, expected, rtol=1e-4, atol=1e-4)


def test_bgr_frames_at_model_size_are_reordered_to_rgb(presses):
    frames, _ = presses
    source = ScriptedSource(np.ascontiguousarray(frames[:, :, :, ::-1]), channel_order="BGR")
    source.connect()
    first = source.read_latest(1)
    to_rgb = frame_converter(first, source.name, TINY.image_size_px)
    np.testing.assert_array_equal(to_rgb(first), frames[0])


def test_wrong_frame_size_is_refused_at_start_naming_both_sizes(model):
    frames = np.zeros((20, 48, 80, 3), np.uint8)
    sensor = LiveSensor(model, ScriptedSource(frames), **BACKEND)
    with pytest.raises(FrameSizeError) as info:
        sensor.start()
    message = str(info.value)
    assert "80x48" in message and "64x64" in message and "1280x1024" in message
    assert "scripted" in message
    assert not sensor.running


def test_backend_that_refuses_the_checkpoint_is_refused_at_start(model, presses):
    from beadsight.inference.runtimes import BackendError

    frames, _ = presses
    source = ScriptedSource(frames)
    with pytest.raises(ValueError, match="no-such-backend"):
        LiveSensor(model, source, LiveSettings(backend="no-such-backend")).start()
    assert not source.opens  # refused before the source was opened
    if not __import__("torch").cuda.is_available():
        sensor = LiveSensor(model, source, LiveSettings(backend="cuda"))
        with pytest.raises(BackendError, match="cuda"):
            sensor.start()
        assert not source.opens  # refused before the source was opened


def test_unplugged_camera_is_reopened_with_exponential_backoff(model, presses):
    frames, _ = presses
    source = ScriptedSource(frames, disconnect_after=25, failed_reopens=2)
    log = StatusLog()
    settings = replace(TORCH, reconnect_initial_s=0.05, reconnect_max_s=0.4)
    sensor = LiveSensor(model, source, settings).open()
    sensor.add_listener(log)
    stream = sensor.readings()
    with sensor:
        readings = list(stream)
    assert sensor.error is None and sensor.status.state == "ended"
    assert len(source.opens) == 4  # first open, two failed reopens, one that worked
    waits = np.diff(source.opens[1:])
    assert waits[0] >= 0.09 and waits[1] >= 0.19  # backoff doubled: 0.05, 0.1, 0.2
    states = log.states
    assert "no_signal" in states and states[-1] == "ended"
    assert states.index("no_signal") < len(states) - 1 - states[::-1].index("ok")  # recovered
    # 25 frames before the loss, 35 after; the window refills after the reconnect
    assert len(readings) == (25 - SPAN + 1) + (len(frames) - 25 - SPAN + 1)


def test_stalled_source_shows_no_signal_then_recovers(model, presses):
    frames, _ = presses
    source = ScriptedSource(frames, stall_after=30)
    log = StatusLog()
    with LiveSensor(model, source, replace(TORCH, no_signal_after_s=0.2)) as sensor:
        sensor.add_listener(log)
        wait_until(lambda: sensor.status.state == "no_signal", 10, "no_signal")
        assert "no frame from scripted" in sensor.status.message
        assert sensor.stats().rate_hz == 0.0
        source.release.set()
        assert sensor.wait(20)
    assert log.states.count("ok") >= 2 and sensor.status.state == "ended"


def test_video_file_source_ends_or_loops(model, presses, tmp_path):
    frames, _ = presses
    video = write_video(tmp_path / "press.avi", frames[:30], fps=60)
    with LiveSensor(model, str(video), **BACKEND) as sensor:
        readings = list(sensor.readings())
    assert sensor.status.state == "ended" and "press.avi" in sensor.status.message
    assert 1 <= len(readings) <= 30 - SPAN + 1
    got = []
    with LiveSensor(model, str(video), replace(TORCH, loop=True)) as sensor:
        for reading in sensor.readings():
            got.append(reading)
            if len(got) == 40:  # more than one pass of the file
                break
    assert sensor.error is None and len(got) == 40


def test_missing_video_file_is_a_clear_error(model, tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.avi"):
        LiveSensor(model, str(tmp_path / "nope.avi"), **BACKEND).start()


def test_recording_to_h5_keeps_every_reading(model, presses, tmp_path):
    frames, force = presses[0][:30], presses[1][:30]  # one press: 16 readings
    path = tmp_path / "rec.h5"
    seen = []
    sensor = LiveSensor(model, ScriptedSource(frames, forces=force), **BACKEND).open()
    sensor.start_recording(path)  # between open() and start(): gets every reading
    sensor.on_update(seen.append)
    with sensor:
        assert sensor.wait(30)
        assert sensor.stop_recording() == path
    with open_readings(path) as rf:
        assert len(rf) == len(seen) == len(frames) - SPAN + 1
        assert rf.geometry == TINY
        assert rf.provenance["source"] == "scripted"
        np.testing.assert_array_equal(rf.timestamp_s, [u.reading.timestamp_s for u in seen])
        np.testing.assert_allclose(rf.force_n, [u.reading.force_n for u in seen], rtol=1e-6)
        np.testing.assert_allclose(rf.cop_mm, [u.reading.cop_mm for u in seen], rtol=1e-5)
        np.testing.assert_allclose(rf.latency_s, [u.latency_s for u in seen], rtol=1e-5)
        np.testing.assert_array_equal(rf.reference_force_n, force[SPAN - 1 :].astype(np.float32))
        np.testing.assert_array_equal(rf.pressure_kpa[7], seen[7].reading.pressure_kpa)


def test_readings_file_errors_name_the_file_and_field(tmp_path, make_dataset):
    dataset = make_dataset()
    with pytest.raises(ReadingsFileError, match=r"tiny\.h5.*'format'"):
        open_readings(dataset)
    with pytest.raises(FileNotFoundError, match="missing.h5"):
        open_readings(tmp_path / "missing.h5")
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(ReadingsFileError, match="notes.h5"):
        open_readings(text)


def test_run_live_headless_stops_after_n_frames(model, presses, tmp_path):
    frames, _ = presses
    lines = []
    sensor = LiveSensor(model, ScriptedSource(frames), replace(TORCH, max_readings=10))
    stats = run_live(
        sensor, LiveRunConfig(viewer=False, output=tmp_path / "r.h5"), echo=lines.append
    )
    assert stats.readings == 10
    assert sensor.status.state == "ended" and "10 readings" in sensor.status.message
    assert f"wrote {tmp_path / 'r.h5'}" in lines
    with open_readings(tmp_path / "r.h5") as rf:
        assert len(rf) == 10  # every reading from the first one
        assert rf.frame_index[0] == SPAN - 1


def test_viewer_state_events_and_record_endpoint(model, presses, tmp_path):
    frames, force = presses
    source = ScriptedSource(frames, forces=force, stall_after=40)
    with (
        LiveSensor(model, source, **BACKEND) as sensor,
        ViewerServer(sensor, port=0, max_fps=10, record_dir=tmp_path) as viewer,
    ):
        wait_until(lambda: sensor.stats().readings >= 20, 20, "20 readings")
        config = json.loads(urllib.request.urlopen(viewer.url + "api/config").read())
        assert config["max_kpa"] == 150 and len(config["colormap"]) == 256
        assert config["source"] == "scripted" and config["backend"].startswith("torch")
        with urllib.request.urlopen(viewer.url + "events") as events:
            first = _next_event(events)
            assert first["status"]["state"] in ("ok", "no_signal")
            assert first["frame"].startswith("data:image/jpeg;base64,")
            assert first["map"].startswith("data:image/png;base64,")
            assert first["reading"]["force_n"] is not None
            assert len(first["trace"]) >= 6  # the history so far
            start = time.monotonic()
            for _ in range(5):
                _next_event(events)
            elapsed = time.monotonic() - start
        assert elapsed >= 5 / 10 * 0.9  # at most max_fps messages per second
        assert set(first["rest"]) == {"origin", "taken_at_s", "requested"}
        # re-take rest button
        asked = _post(viewer.url + "api/rest", {})["rest"]
        assert asked["requested"] is True and sensor.rest_requested
        # record button
        bad = urllib.request.Request(viewer.url + "api/record", data=b"action=start")
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(bad)
        assert info.value.code == 415
        assert _post(viewer.url + "api/record", {"action": "start"})["recording"]["path"]
        source.release.set()
        assert sensor.wait(30)
        stopped = _post(viewer.url + "api/record", {"action": "stop"})
        assert stopped["recording"] is None
        state = json.loads(urllib.request.urlopen(viewer.url + "api/state").read())
        assert state["status"]["state"] == "ended" and state["status"]["signal"] is False
    files = list(tmp_path.glob("beadsight-*.h5"))
    assert len(files) == 1
    with open_readings(files[0]) as rf:
        assert len(rf) == len(frames) - 40  # every reading after the button was pressed


def _next_event(stream) -> dict:
    while True:
        line = stream.readline()
        assert line, "event stream closed"
        if line.startswith(b"data: "):
            return json.loads(line[6:])


def _post(url: str, body: dict) -> dict:
    request = urllib.request.Request(
        url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"}
    )
    return json.loads(urllib.request.urlopen(request).read())


def test_viewer_images_use_the_fixed_colour_scale():
    from beadsight.live.outputs.colormap import colormap_bgr
    from beadsight.live.outputs.viewer.server import contact_outlines, encode_map

    lut = colormap_bgr()
    kpa = np.zeros((64, 64), np.float32)
    kpa[20:30, 20:30] = 75.0
    kpa[0, 0] = 1e6  # saturates, never rescales the map
    png = encode_map(kpa, 150.0, lut)
    image = cv2.imdecode(np.frombuffer(base64.b64decode(png.split(",", 1)[1]), np.uint8), 1)
    np.testing.assert_array_equal(image[25, 25], lut[127])
    np.testing.assert_array_equal(image[50, 50], lut[0])
    np.testing.assert_array_equal(image[0, 0], lut[255])
    outline = contact_outlines(kpa > 10)
    assert len(outline) == 2  # the square, then the single saturated pixel
    square = np.array(outline[0])
    np.testing.assert_allclose(square.min(0), [20.5 / 64, 20.5 / 64], atol=1e-3)
    np.testing.assert_allclose(square.max(0), [29.5 / 64, 29.5 / 64], atol=1e-3)


def test_sim_source_paces_simulated_frames_with_true_force(model):
    got = []
    with LiveSensor(model, "sim", replace(TORCH, source_fps=30, seed=3)) as sensor:
        assert sensor.source.name == "sim (seed 3)"
        for update in sensor.updates():
            got.append(update)
            if len(got) == 10:
                break
    assert sensor.error is None
    assert all(math.isfinite(u.reference_force_n) for u in got)
    assert all(u.frame_rgb.shape == (64, 64, 3) and u.frame_rgb.dtype == np.uint8 for u in got)
    frames = np.stack([u.frame_rgb for u in got])
    assert frames.std(axis=0).mean() > 0  # frames change (sensor noise, beads)


def test_virtual_camera_unplug_is_reported_and_reopened(model):
    from beadsight.devices.virtual.camera import VirtualCamera

    frames, _ = press_frames(presses=1, per_press=30)
    frames_bgr = np.ascontiguousarray(frames[:, :, :, ::-1])
    count = 0

    def render():
        nonlocal count
        count += 1
        return frames_bgr[count % len(frames_bgr)]

    camera = VirtualCamera(render, fps=60)
    log = StatusLog()
    sensor = LiveSensor(
        model, camera, replace(TORCH, reconnect_initial_s=0.05, reconnect_max_s=0.2)
    )
    sensor.add_listener(log)
    with sensor:
        readings = sensor.readings()
        for _ in range(5):
            next(readings)
        camera.unplug()
        wait_until(lambda: sensor.status.state == "no_signal", 10, "no_signal after unplug")
        # recovered: the reopened camera refilled the window (the iterator's next readings
        # may still be ones queued before the unplug, on a loaded machine)
        wait_until(lambda: sensor.status.state == "ok", 10, "ok after the reopen")
        for _ in range(5):  # and readings go on
            next(readings)
        readings.close()
    assert any(s == "no_signal" and "unplugged" in m and "reopening" in m for s, m in log.changes)
    assert log.states[-2] == "ok"  # recovered before the final "stopped"
    assert sensor.error is None


def test_cli_live_headless_writes_readings(model, presses, tmp_path):
    frames, _ = presses
    video = write_video(tmp_path / "v.avi", frames[:30], fps=60)
    checkpoint = model.save(tmp_path / "tiny.pt")
    out = tmp_path / "readings.h5"
    more = ["--no-viewer", "--output", str(out), "--frames", "5"]
    code = main(live_argv(checkpoint, video, *more, "--loop"))  # --loop: 5 readings always come
    assert code == 0
    with open_readings(out) as rf:
        assert len(rf) == 5
        assert rf.provenance["checkpoint"] == str(checkpoint)


def test_cli_live_reports_bad_source_size_as_one_line(model, tmp_path, capsys):
    video = write_video(tmp_path / "wide.avi", np.zeros((20, 48, 80, 3), np.uint8))
    checkpoint = model.save(tmp_path / "tiny.pt")
    code = main(live_argv(checkpoint, video, "--no-viewer"))
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "80x48" in err[0] and "64x64" in err[0]


def test_cli_live_sim_headless_straight_to_mcap(model, tmp_path, capsys):
    checkpoint = model.save(tmp_path / "tiny.pt")
    out = tmp_path / "sim.mcap"
    code = main(
        [
            *live_sim_args(checkpoint),
            "--output",
            str(out),
            "--frames",
            "4",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed and "final: " in printed
    from mcap.reader import make_reader

    with open(out, "rb") as f:
        topics = [c.topic for _s, c, _m in make_reader(f).iter_messages()]
    assert topics.count("/beadsight/pressure") == 4
    assert topics.count("/beadsight/reference_force") == 4  # the simulator's true force


def test_cli_live_user_errors_are_one_line(model, tmp_path, capsys, monkeypatch):
    import beadsight.assets

    monkeypatch.setattr(beadsight.assets, "SHIPPED_MODEL", "absent.pt")
    assert main(["live", "--no-viewer"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "absent.pt" in err[0] and "--checkpoint" in err[0]
    checkpoint = model.save(tmp_path / "tiny.pt")
    assert main(["live", "--checkpoint", str(checkpoint), "--backend", "nope", "--no-viewer"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    assert main(["live", "--checkpoint", str(tmp_path / "missing.pt"), "--no-viewer"]) == 1
    assert "missing.pt" in capsys.readouterr().err
