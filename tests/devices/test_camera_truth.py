"""Camera truth: duplicated and dropped frames and a slow camera, counted exactly against
faults injected into a virtual camera, and reported in live stats."""

from __future__ import annotations

import math

import numpy as np
import pytest

from beadsight.devices.virtual import SteppedClock, VirtualCamera

FPS = 30.0


def counting_camera(fps: float = FPS, **options) -> VirtualCamera:
    """A camera whose every frame differs from the one before (a frame counter)."""
    count = [0]

    def render() -> np.ndarray:
        count[0] += 1
        image = np.zeros((8, 8, 3), np.uint8)
        image[0, 0] = (count[0] % 256, count[0] // 256 % 256, 0)
        return image

    return VirtualCamera(render, fps=fps, name="counting", **options)


def read_frames(camera: VirtualCamera, n: int) -> list:
    return [camera.read(2.0) for _ in range(n)]


def test_duplicated_and_dropped_frames_are_counted_exactly():
    with counting_camera(clock=SteppedClock()) as camera:  # 30 fps: 17 ms of jitter is a drop
        read_frames(camera, 5)
        camera.duplicate(4)
        read_frames(camera, 10)
        camera.drop(3)
        read_frames(camera, 25)
        stats = camera.stats
    assert stats.duplicated == 4
    assert stats.dropped == 3
    assert not stats.slow and stats.requested_fps == FPS
    assert stats.delivered_fps == pytest.approx(FPS, rel=0.1)


def test_a_camera_slower_than_asked_is_reported_slow(caplog):
    # 5 fps asked, 4 delivered (80 %): frames 1.25 periods apart, under the 1.5-period gap
    # that counts as lost. On a stepped clock, not the host's: host jitter on a loaded
    # machine (+73 ms seen at 5 fps, +8 ms at 30 fps) made such gaps count as drops
    with counting_camera(fps=5.0, clock=SteppedClock()) as camera:
        camera.deliver_at(4.0)
        read_frames(camera, 12)  # > 2 s of frames
        stats = camera.stats
    assert stats.slow and stats.delivered_fps == pytest.approx(4.0, rel=0.1)
    assert stats.dropped == 0 and stats.duplicated == 0  # slower is not lossy
    assert "delivers" in caplog.text and "5 fps was requested" in caplog.text


def test_live_stats_carry_the_camera_truth():
    from beadsight.live.stats import LiveStats

    base = LiveStats(0, 0, 0.0, 0.0, math.nan, math.nan, math.nan, math.nan, 0, 0)
    with counting_camera() as camera:
        camera.duplicate(2)
        read_frames(camera, 40)
        stats = base.with_camera(camera)
    assert stats.camera_duplicated == 2 and stats.requested_fps == FPS
    assert "duplicated 2" in stats.summary()
    assert base.with_camera(object()) is base  # a source that does not tell
