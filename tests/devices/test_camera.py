"""OpenCVCamera on real MJPG video files, and VirtualCamera's fault paths."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from beadsight.devices import (
    CameraConfigError,
    CameraDisconnectedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    OpenCVCamera,
)
from beadsight.devices.virtual import VirtualCamera

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
