"""Live sources are cameras: what a --source names."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from helpers.live import (
    TORCH,
    press_frames,
    tiny_model,
    write_video,
)

from beadsight.devices import Camera, CameraEndedError, OpenCVCamera
from beadsight.devices.virtual import SimCamera, VirtualCamera
from beadsight.live.sensor import LiveSensor
from beadsight.live.sources import open_camera

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads


def test_source_specs_name_cameras(tmp_path):
    video = tmp_path / "v.avi"
    sim = open_camera("sim", image_size=64, fps=20, seed=4)
    assert isinstance(sim, SimCamera) and sim.name == "sim (seed 4)" and sim.requested_fps == 20
    for spec in (3, "3", " 3 "):
        camera = open_camera(spec, image_size=64)
        assert isinstance(camera, OpenCVCamera) and camera.source == 3 and not camera.is_file
        assert camera.requested == (1280, 1024)  # the reference camera's mode
    device = open_camera("/dev/video7", image_size=64, fps=60, any_size=True)
    assert device.source == "/dev/video7" and not device.is_file
    assert device.requested == (None, None) and device.requested_fps == 60
    file = open_camera(video, image_size=64, loop=True)
    assert file.is_file and file.loop and file.requested == (None, None)
    assert file.name == f"video {video}"
    mine = VirtualCamera(lambda: np.zeros((8, 8, 3), np.uint8))
    assert open_camera(mine, image_size=64) is mine
    with pytest.raises(TypeError, match="source must be a camera index"):
        open_camera(object(), image_size=64)
    assert all(isinstance(c, Camera) for c in (sim, device, file, mine))


def test_live_reads_a_looping_video_file_through_opencv(tmp_path):
    frames, _ = press_frames(presses=1, per_press=20)
    video = write_video(tmp_path / "loop.avi", frames, fps=120)
    got = []
    with LiveSensor(tiny_model(), str(video), replace(TORCH, loop=True)) as sensor:
        assert isinstance(sensor.source, OpenCVCamera) and sensor.source.loop
        for reading in sensor.readings():
            got.append(reading)
            if len(got) == 30:  # more frames than one pass of the file
                break
    assert sensor.error is None
    assert sensor.source.stats.captured > len(frames)
    assert np.all(np.diff([r.timestamp_s for r in got]) > 0)


def test_sim_camera_ends_after_its_presses_or_loops():
    with SimCamera(32, seed=5, presses=1, realtime=False) as cam:
        frames = []
        with pytest.raises(CameraEndedError, match=r"sim \(seed 5\): ended after"):
            while True:
                frames.extend(cam.async_read(timeout_s=30.0))
    assert len(frames) > 30 and [f.index for f in frames] == list(range(len(frames)))
    assert all(math.isfinite(f.reference_force_n) for f in frames)
    assert max(f.reference_force_n for f in frames) > 0.5  # the press shows in the true force
    with SimCamera(32, seed=5, presses=1, realtime=False, loop=True) as cam:
        count = 0
        while count <= len(frames):
            count += len(cam.async_read(timeout_s=30.0))
    assert count > len(frames)  # played on past the session's end
