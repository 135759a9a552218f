"""Shared pieces of the live/outputs/viewer/stream/rosbag tests: tiny models, synthetic presses, and
a scripted camera (one that never skips frames and can fail on cue)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.devices import (
    CameraDisconnectedError,
    CameraEndedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
)
from beadsight.devices.base import DeviceContext, Frame
from beadsight.live.settings import LiveSettings
from helpers.synthetic_presses import make_press_arrays, synthetic_press_frames

TINY = SensorGeometry(image_size_px=64)
SPAN = 15  # frames per window of tiny_model() (15 frames, stride 1)
TORCH = LiveSettings(backend="torch", precision="fp32")  # fast to build; "auto" times candidates
BACKEND = {"settings": TORCH}


def live_argv(checkpoint: Path, source: Path, *more: str) -> list[str]:
    """``beadsight live`` arguments for ``checkpoint`` on ``source`` with fp32 torch."""
    return ["live", "--checkpoint", str(checkpoint), "--source", str(source), *TORCH_FLAGS, *more]


TORCH_FLAGS = ("--backend", "torch", "--precision", "fp32")


def tiny_model(frames: int = SPAN, seed: int = 0, scale_kpa: float = 10.0) -> PressureModel:
    torch.manual_seed(seed)
    meta = CheckpointMeta(
        model=ModelConfig(frames=frames, width=8),
        geometry=TINY,
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=scale_kpa,
    )
    return PressureModel.create(meta)


def press_frames(presses: int = 2, per_press: int = 30, seed: int = 0):
    """(N, 64, 64, 3) uint8 RGB frames of finger presses and their (N,) forces in N."""
    rng = np.random.default_rng(seed)
    force, position = make_press_arrays(presses, per_press, TINY, rng)
    return synthetic_press_frames(force, position, TINY, rng), force


def write_video(path: Path, frames_rgb: np.ndarray, fps: float = 30.0) -> Path:
    """Write RGB frames to a lossless-enough MJPG .avi (OpenCV), returns the path."""
    h, w = frames_rgb.shape[1:3]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened(), f"OpenCV cannot write {path}"
    for frame in frames_rgb:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


class ScriptedSource(DeviceContext):
    """A :class:`beadsight.devices.Camera` that hands out ``frames`` in order, one per
    read, never skipping (so every window is known).

    Timestamps are ``t0 + i / fps`` with ``t0`` in the past. Faults on cue:
    ``disconnect_after=k``: after frame k-1 the camera raises CameraDisconnectedError (an
    unplugged camera) until reconnected; ``failed_reopens``: that many reconnects fail
    first; ``stall_after=k``: before frame k it delivers nothing (DeviceTimeoutError)
    until ``release`` is set.
    """

    def __init__(
        self,
        frames: np.ndarray,
        fps: float = 30.0,
        channel_order: str = "RGB",
        forces: np.ndarray | None = None,
        disconnect_after: int | None = None,
        failed_reopens: int = 0,
        stall_after: int | None = None,
    ):
        self.name = "scripted"
        self.frames, self.fps, self.channel_order = frames, fps, channel_order
        self.height, self.width = frames.shape[1:3]
        self.forces = forces
        self.disconnect_after = disconnect_after
        self.failed_reopens = failed_reopens
        self.stall_after = stall_after
        self.release = threading.Event()
        self.t0 = time.time() - len(frames) / fps - 1.0
        self.next = 0
        self.opens: list[float] = []  # monotonic times of connect() calls
        self.connected = False
        self.closed = threading.Event()

    def connect(self) -> None:
        self.opens.append(time.monotonic())
        self.closed.clear()
        if len(self.opens) > 1 and self.failed_reopens > 0:
            self.failed_reopens -= 1
            raise DeviceNotConnectedError(self.name, "camera still unplugged")
        self.connected = True

    def close(self) -> None:
        self.connected = False
        self.closed.set()

    def async_read(self, timeout_s: float | None = None, max_frames: int | None = None):
        if not self.connected:
            raise CameraDisconnectedError(self.name, "camera unplugged")
        i = self.next
        if i >= len(self.frames):
            raise CameraEndedError(self.name, f"ended after {i} frames")
        if i == self.stall_after and not self.release.wait(timeout_s):
            raise DeviceTimeoutError(self.name, f"no new frame within {timeout_s:g} s")
        self.next += 1
        if self.disconnect_after is not None and self.next == self.disconnect_after:
            self.connected = False
            self.disconnect_after = None
        force = math.nan if self.forces is None else float(self.forces[i])
        t_unix = self.t0 + i / self.fps
        t_mono = time.monotonic() - (time.time() - t_unix)
        return [Frame(self.frames[i], i, t_mono, t_unix, self.channel_order, force)]

    def read(self, timeout_s: float | None = None) -> Frame:
        return self.async_read(timeout_s)[0]

    read_latest = read


class StatusLog:
    """A listener that records every status change as (state, message)."""

    def __init__(self):
        self.changes: list[tuple[str, str]] = []

    @property
    def states(self) -> list[str]:
        return [state for state, _ in self.changes]

    def push(self, update) -> None:
        pass

    def status(self, status) -> None:
        self.changes.append((status.state, status.message))

    def finish(self) -> None:
        pass


def wait_until(predicate, timeout_s: float = 20.0, what: str = "condition") -> None:
    """Poll ``predicate`` (for state owned by other threads) until true or fail."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def live_sim_args(checkpoint) -> list[str]:
    """``beadsight live`` on the simulated sensor with ``checkpoint`` on eager torch fp32 (fast
    to build), headless: the start of a test's command line."""
    args = "live --checkpoint {} --source sim --backend torch --precision fp32 --no-viewer"
    return [a.format(checkpoint) for a in args.split()]
