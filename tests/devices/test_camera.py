"""The cameras: OpenCVCamera on real MJPG video files, the virtual and simulated cameras,
one Camera API over all of them, and their fault paths."""

from __future__ import annotations

import logging
import math
import time

import cv2
import numpy as np
import pytest

from beadsight.devices import (
    Camera,
    CameraConfigError,
    CameraDisconnectedError,
    CameraEndedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Frame,
    OpenCVCamera,
    VideoFileNotFoundError,
)
from beadsight.devices.opencv import is_device_path
from beadsight.devices.virtual import FrameClock, PlaybackCamera, SimCamera, VirtualCamera

WIDTH, HEIGHT = 64, 48
LEVEL_STEP = 12  # grey level added per frame, so frame k can be recognised after MJPG


def write_video(path, frames: int, fps: float) -> None:
    """An MJPG .avi of flat grey frames whose level encodes the frame number."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (WIDTH, HEIGHT))
    assert writer.isOpened()
    for k in range(frames):
        writer.write(np.full((HEIGHT, WIDTH, 3), 10 + LEVEL_STEP * k, np.uint8))
    writer.release()


def frame_number(image: np.ndarray) -> int:
    return round((float(image.mean()) - 10) / LEVEL_STEP)


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "press.avi"
    write_video(path, frames=12, fps=50)
    return path


def flat(level: int = 100):
    return lambda: np.full((HEIGHT, WIDTH, 3), level, np.uint8)


# --- video files --------------------------------------------------------------------------
def test_file_frames_in_order_then_end_of_file(video):
    with OpenCVCamera(str(video), width=WIDTH, height=HEIGHT, realtime=False) as cam:
        assert (cam.width, cam.height, cam.fps) == (WIDTH, HEIGHT, 50)
        frames = [cam.read(timeout_s=2.0) for _ in range(12)]
        assert [f.index for f in frames] == list(range(12))
        assert [frame_number(f.image) for f in frames] == list(range(12))
        assert frames[0].image.shape == (HEIGHT, WIDTH, 3) and frames[0].image.dtype == np.uint8
        with pytest.raises(CameraDisconnectedError, match="end of file after 12 frames"):
            cam.read(timeout_s=2.0)
        assert cam.stats.dropped == 0 and cam.stats.overflowed == 0


def test_file_plays_at_its_fps_with_timestamps(video):
    start = time.monotonic()
    with OpenCVCamera(str(video), width=None, height=None) as cam:
        frames = [cam.read(timeout_s=2.0) for _ in range(12)]
    assert time.monotonic() - start >= 11 / 50 - 0.01
    gaps = np.diff([f.t_mono for f in frames])
    assert np.median(gaps) == pytest.approx(1 / 50, abs=0.008)
    assert all(abs(f.t_unix - time.time()) < 10 for f in frames)


def test_small_queue_does_not_lose_file_frames(video):
    with OpenCVCamera(
        str(video), width=WIDTH, height=HEIGHT, realtime=False, queue_frames=2
    ) as cam:
        time.sleep(0.2)  # the reader waits for us instead of overwriting frames
        assert [cam.read(timeout_s=2.0).index for _ in range(12)] == list(range(12))


def test_read_latest_never_repeats_a_frame(video):
    with OpenCVCamera(str(video), width=WIDTH, height=HEIGHT) as cam:
        seen = []
        while True:
            try:
                seen.append(cam.read_latest(timeout_s=2.0).index)
            except CameraDisconnectedError:
                break
            time.sleep(0.05)
        assert len(seen) >= 2
        assert all(b > a for a, b in zip(seen, seen[1:], strict=False))
        assert cam.stats.skipped > 0
        assert cam.stats.skipped + cam.stats.delivered == 12


def test_resolution_mismatch_names_camera_and_both_sizes(video):
    with pytest.raises(CameraConfigError) as err:
        OpenCVCamera(str(video), width=1280, height=1024).connect()
    message = str(err.value)
    assert "camera press.avi" in message
    assert "64x48" in message and "1280x1024" in message


def test_missing_file_and_absent_camera():
    with pytest.raises(DeviceNotConnectedError, match="nope.avi does not exist"):
        OpenCVCamera("/tmp/nope.avi").connect()
    with pytest.raises(
        DeviceNotConnectedError, match=r"camera 97: could not be opened.*ls /dev/video"
    ):
        OpenCVCamera(97).connect()


def test_read_before_connect_is_an_error(video):
    cam = OpenCVCamera(str(video))
    with pytest.raises(DeviceNotConnectedError, match="not connected"):
        cam.read(timeout_s=0.1)


# --- virtual camera ----------------------------------------------------------------------
def test_virtual_camera_stall_counts_dropped_frames():
    with VirtualCamera(flat(), fps=50) as cam:
        cam.read(timeout_s=1.0)
        cam.stall(0.3)  # ~15 frame periods without frames
        time.sleep(0.5)
        assert cam.stats.dropped >= 10
        assert cam.stats.overflowed == 0


def test_virtual_camera_queue_overflow_is_counted():
    with VirtualCamera(flat(), fps=100, queue_frames=4) as cam:
        time.sleep(0.3)
        first = cam.read(timeout_s=1.0)
        assert cam.stats.overflowed > 0
        assert first.index > 0  # the oldest frames were pushed out


def test_virtual_camera_unplug_drains_then_raises():
    with VirtualCamera(flat(), fps=100) as cam:
        time.sleep(0.1)
        cam.unplug()
        time.sleep(0.05)
        queued = 0
        with pytest.raises(
            CameraDisconnectedError, match="virtual camera: stopped delivering frames"
        ):
            while True:
                cam.read(timeout_s=1.0)
                queued += 1
        assert queued >= 3
        with pytest.raises(CameraDisconnectedError):
            cam.read_latest(timeout_s=1.0)


def test_virtual_camera_refuses_unsupported_size():
    with pytest.raises(
        CameraConfigError, match="delivers 64x48 frames but 1280x1024 was requested"
    ):
        VirtualCamera(flat(), width=1280, height=1024).connect()


def test_virtual_camera_read_latest_waits_for_a_new_frame():
    with VirtualCamera(flat(), fps=20) as cam:
        a = cam.read_latest(timeout_s=1.0)
        b = cam.read_latest(timeout_s=1.0)
        assert b.index > a.index
        assert b.t_mono - a.t_mono > 0.5 / 20


def test_virtual_camera_timeout_when_stalled():
    with VirtualCamera(flat(), fps=20) as cam:
        cam.read_latest(timeout_s=1.0)
        cam.stall(5.0)  # applies after the frame already scheduled
        time.sleep(0.1)
        cam.read_latest(timeout_s=1.0)  # that scheduled frame
        with pytest.raises(DeviceTimeoutError, match="no new frame within 0.2 s"):
            cam.read_latest(timeout_s=0.2)


# --- one Camera API over every kind of camera ------------------------------------------------
def _video_camera(path):
    return OpenCVCamera(str(path), width=None, height=None)


def _sim_camera(_path):
    return SimCamera(image_size=32, fps=60, seed=1)


def _virtual_camera(_path):
    return VirtualCamera(flat(), fps=60)


@pytest.mark.parametrize("make", [_video_camera, _sim_camera, _virtual_camera])
def test_every_camera_has_the_same_api(video, make):
    camera = make(video)
    assert isinstance(camera, Camera)
    with camera as cam:
        assert cam.width > 0 and cam.height > 0 and cam.fps > 0
        first = cam.read(timeout_s=5.0)
        batch = cam.async_read(timeout_s=5.0, max_frames=3)
        latest = cam.read_latest(timeout_s=5.0)
    frames = [first, *batch, latest]
    assert all(isinstance(f, Frame) for f in frames)
    assert all(f.image.shape == (cam.height, cam.width, 3) for f in frames)
    assert all(f.image.dtype == np.uint8 for f in frames)
    assert first.index == 0 and 1 <= len(batch) <= 3
    indices = [f.index for f in frames]
    assert indices == sorted(set(indices))  # none handed out twice, in capture order
    assert np.all(np.diff([f.t_unix for f in frames]) > 0)
    assert np.all(np.diff([f.t_mono for f in frames]) >= 0)
    assert cam.stats.captured >= len(frames)


def test_sim_camera_frames_carry_the_true_force():
    with SimCamera(image_size=32, fps=60, seed=2) as cam:
        frames = [cam.read(timeout_s=5.0) for _ in range(5)]
    assert cam.name == "sim (seed 2)"
    assert all(f.channel_order == "RGB" and math.isfinite(f.reference_force_n) for f in frames)


def test_video_file_frames_have_no_reference_force(video):
    with OpenCVCamera(str(video), width=WIDTH, height=HEIGHT, realtime=False) as cam:
        frame = cam.read(timeout_s=2.0)
    assert frame.channel_order == "BGR" and math.isnan(frame.reference_force_n)
    assert frame.timestamp_s == frame.t_unix


def test_async_read_returns_every_new_frame_and_counts_the_skipped(video):
    with OpenCVCamera(str(video), width=WIDTH, height=HEIGHT, realtime=False) as cam:
        assert cam.read(timeout_s=2.0).index == 0
        wait_for(lambda: cam.ended)  # the whole file is queued now
        frames = cam.async_read(timeout_s=2.0, max_frames=5)
        assert [f.index for f in frames] == [7, 8, 9, 10, 11]
        assert [frame_number(f.image) for f in frames] == [7, 8, 9, 10, 11]
        assert cam.stats.skipped == 6  # frames 1-6 were passed over, and counted
        with pytest.raises(CameraEndedError, match="end of file after 12 frames"):
            cam.async_read(timeout_s=2.0)


def test_read_latest_never_returns_a_stale_frame_as_new(video):
    """Whichever read handed a frame out, read_latest waits for a newer one, and raises
    (ended, timed out) rather than hand the last frame out again."""
    with OpenCVCamera(str(video), width=WIDTH, height=HEIGHT, realtime=False) as cam:
        wait_for(lambda: cam.ended)  # every frame is captured; the newest is frame 11
        assert cam.read(timeout_s=2.0).index == 0
        assert cam.read_latest(timeout_s=2.0).index == 11
        with pytest.raises(CameraEndedError):
            cam.read_latest(timeout_s=0.5)  # frame 11 again would be stale
        with pytest.raises(CameraEndedError):
            cam.read(timeout_s=0.5)  # frames 1-10 are older than what was handed out
    with VirtualCamera(flat(), fps=20) as cam:
        seen = cam.read_latest(timeout_s=1.0)
        cam.stall(5.0)  # after the frame already scheduled, nothing new comes
        later = [cam.read_latest(timeout_s=1.0)]
        with pytest.raises(DeviceTimeoutError):
            later.append(cam.read_latest(timeout_s=0.3))
        assert later[0].index > seen.index
        cam.unplug()
        with pytest.raises(CameraDisconnectedError):
            cam.read_latest(timeout_s=2.0)


def test_looping_file_keeps_counting(video):
    with OpenCVCamera(str(video), width=None, height=None, realtime=False, loop=True) as cam:
        frames = [cam.read(timeout_s=2.0) for _ in range(30)]
    assert [f.index for f in frames] == list(range(30))
    assert [frame_number(f.image) for f in frames] == [k % 12 for k in range(30)]


def test_played_frames_end_or_loop():
    images = [np.full((HEIGHT, WIDTH, 3), 10 + LEVEL_STEP * k, np.uint8) for k in range(4)]
    with PlaybackCamera(lambda: [(im, float(k)) for k, im in enumerate(images)], fps=200) as cam:
        frames = [cam.read(timeout_s=2.0) for _ in range(4)]
        with pytest.raises(CameraEndedError, match="playback: ended after 4 frames"):
            cam.read(timeout_s=2.0)
    assert [f.reference_force_n for f in frames] == [0.0, 1.0, 2.0, 3.0]
    with PlaybackCamera(lambda: images, fps=200, loop=True) as cam:
        frames = [cam.read(timeout_s=2.0) for _ in range(10)]
    assert [frame_number(f.image) for f in frames] == [k % 4 for k in range(10)]
    assert [f.index for f in frames] == list(range(10))


def test_a_frame_clock_stamps_played_frames_one_period_apart_however_they_are_read():
    """Played as fast as read, on a FrameClock: capture stamps are the camera's own time
    (what rest references and health are timed by), not when the host got round to it."""
    images = [np.full((HEIGHT, WIDTH, 3), 10 + LEVEL_STEP * k, np.uint8) for k in range(5)]
    clock = FrameClock(30)
    with PlaybackCamera(lambda: images, fps=30, realtime=False, queue_frames=1, clock=clock) as cam:
        frames = []
        for k in range(5):
            frames.append(cam.read(timeout_s=2.0))
            time.sleep(0.02 * k)  # uneven reads
    assert [frame_number(f.image) for f in frames] == list(range(5))
    assert np.allclose(np.diff([f.t_mono for f in frames]), 1 / 30, atol=1e-9)
    assert np.allclose(np.diff([f.t_unix for f in frames]), 1 / 30, atol=1e-6)
    with pytest.raises(ValueError, match="fps must be > 0"):
        FrameClock(0)


def test_unplugged_camera_reconnects_with_indices_counting_on():
    with VirtualCamera(flat(), fps=100) as cam:
        before = cam.read(timeout_s=1.0)
        cam.unplug()
        with pytest.raises(CameraDisconnectedError, match="unplugged"):
            while True:
                cam.read(timeout_s=1.0)
        cam.close()
        cam.connect()  # plugged back in
        after = cam.read_latest(timeout_s=1.0)
    assert after.index > before.index and after.t_unix > before.t_unix


def test_absent_camera_index_and_device_path_are_named():
    """No camera exists here: opening one fails with an error naming it and a hint."""
    with pytest.raises(DeviceNotConnectedError) as info:
        OpenCVCamera(63, width=None, height=None).connect()
    assert str(info.value).startswith("camera 63: could not be opened")
    assert "hint: is it plugged in?" in str(info.value)
    with pytest.raises(DeviceNotConnectedError, match=r"camera /dev/video63: could not be opened"):
        OpenCVCamera("/dev/video63").connect()
    assert is_device_path("/dev/video63") and not is_device_path("press.avi")


def test_missing_video_file_is_a_file_not_found_error(tmp_path):
    with pytest.raises(VideoFileNotFoundError) as info:
        OpenCVCamera(tmp_path / "gone.avi").connect()
    assert isinstance(info.value, FileNotFoundError)
    assert str(info.value) == f"camera gone.avi: video file {tmp_path / 'gone.avi'} does not exist"


def test_bad_frames_from_a_renderer_end_the_stream_with_the_reason():
    with pytest.raises(ValueError, match=r"virtual camera: frames must be \(H, W, 3\) uint8"):
        VirtualCamera(lambda: np.zeros((8, 8), np.uint8)).connect()
    calls = 0

    def render():
        nonlocal calls
        calls += 1
        return np.zeros((8, 8, 3), np.uint8 if calls < 3 else np.float32)

    with VirtualCamera(render, fps=100) as cam:
        with pytest.raises(CameraDisconnectedError, match="capture failed"):
            while True:
                cam.read(timeout_s=1.0)


def wait_for(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_capture_gaps_under_load_are_summarised_every_10_s(caplog):
    """Issue 26: 38 gap lines in 60 s flooded the console. 60 s at 30 fps with a 100 ms gap
    every 1.5 s (40 gaps): the first is logged at once, the rest as one line per 10 s with
    counts, and every lost frame is still counted."""
    cam = VirtualCamera(flat(), fps=30)
    frame, gaps = 0, 0  # t = frame / 30 s, exact
    with caplog.at_level(logging.WARNING, logger="beadsight.devices.camera"):
        while frame < 60 * 30:
            cam._count_gap(frame / 30)
            if frame % 45 == 44:  # every 1.5 s: 3 frame periods without a frame
                frame, gaps = frame + 3, gaps + 1
            else:
                frame += 1
        cam._count_gap(frame / 30)  # the frame after the last gap
    lines = [r.getMessage() for r in caplog.records]
    assert gaps == 40 and len(lines) == 6, lines
    assert lines[0] == f"{cam.name}: 100 ms capture gap, ~2 frame(s) dropped"
    assert lines[1] == (
        f"{cam.name}: 7 capture gaps in the last 10 s, ~14 frame(s) dropped, longest 100 ms"
    )
    summarised = sum(int(line.split(": ")[1].split()[0]) for line in lines[1:])
    assert 1 + summarised <= gaps and cam.stats.dropped == 2 * gaps
