"""Shared fixtures: tiny synthetic datasets and models (64x64 frames, U-Net width 8)."""

from __future__ import annotations

import dataclasses
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.dataset import DatasetWriter
from beadsight.geometry import mm_to_px

TINY = SensorGeometry(image_size_px=64)


def pytest_configure(config):
    """Let the Ctrl-C tests' children see SIGINT even when pytest runs as a background job.

    A non-interactive shell starts background jobs (``nohup .ci/run &``) with SIGINT ignored,
    and an ignored signal is inherited by every child, so ``beadsight collect`` or
    ``beadsight live`` would never receive the test's Ctrl-C and run to the end.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def synthetic_press_frames(force_n, position_mm, geometry, rng):
    """(N, S, S, 3) uint8 RGB frames: noisy texture darkened under the finger.

    A deliberately learnable stand-in for the simulator: the dark blob's position
    and depth follow the finger position and force.
    """
    s = geometry.image_size_px
    n = len(force_n)
    base = rng.integers(60, 200, size=(s, s, 3)).astype(np.float32)
    rows, cols = np.mgrid[0:s, 0:s] + 0.5
    rc = mm_to_px(position_mm, geometry)
    radius_px = geometry.finger_radius_mm / geometry.mm_per_px
    d2 = (rows[None] - rc[:, 0, None, None]) ** 2 + (cols[None] - rc[:, 1, None, None]) ** 2
    blob = np.exp(-d2 / (2 * radius_px**2)) * np.clip(force_n, 0, None)[:, None, None] * 6.0
    frames = base[None] - blob[..., None] + rng.normal(0, 3, size=(n, s, s, 3))
    return np.clip(frames, 0, 255).astype(np.uint8)


def make_press_arrays(presses: int, frames_per_press: int, geometry, rng):
    """Force ramps (0 -> peak -> 0) at random positions: force_n (N,), position_mm (N, 2)."""
    peak = rng.uniform(5, 20, size=presses)
    xy = rng.uniform(-geometry.press_range_mm, geometry.press_range_mm, size=(presses, 2))
    phase = np.linspace(0, 1, frames_per_press)
    shape = np.clip(np.sin(np.pi * (phase - 0.2) / 0.6), 0, None) * ((phase > 0.2) & (phase < 0.8))
    force = (peak[:, None] * shape[None]).reshape(-1)
    position = np.repeat(xy, frames_per_press, axis=0)
    return force, position


@pytest.fixture
def make_dataset(tmp_path: Path):
    """Factory: make_dataset(presses=6, frames_per_press=40, image_size=64, ...) -> Path."""

    def make(
        presses: int = 6,
        frames_per_press: int = 40,
        image_size: int = 64,
        seed: int = 0,
        name: str = "tiny.h5",
        fps: float = 30.0,
    ) -> Path:
        geometry = SensorGeometry(image_size_px=image_size)
        rng = np.random.default_rng(seed)
        force, position = make_press_arrays(presses, frames_per_press, geometry, rng)
        frames = synthetic_press_frames(force, position, geometry, rng)
        n = len(force)
        t = 1.7e9 + np.arange(n) / fps
        path = tmp_path / name
        with DatasetWriter(path, geometry, fps=fps, provenance={"source": "test-fixture"}) as w:
            w.append(frames, force, position, np.ones(n, bool), t)
        return path

    return make


@pytest.fixture
def tiny_model() -> PressureModel:
    """An untrained width-8, 15-frame model for 64x64 frames."""
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(frames=15, width=8),
        geometry=TINY,
        pixel_mean=[120.0, 120.0, 120.0],
        pixel_std=[40.0, 40.0, 40.0],
        output_scale_kpa=10.0,
    )
    return PressureModel.create(meta)


@pytest.fixture(scope="session")
def probe_model() -> PressureModel:
    """An untrained width-8, 15-frame model for 64x64 frames (output scale 10 kPa), shared by
    a session: inference tests must not change it."""
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(frames=15, width=8), geometry=TINY,
        pixel_mean=[120.0] * 3, pixel_std=[40.0] * 3, output_scale_kpa=10.0,
    )  # fmt: skip
    return PressureModel.create(meta)


@pytest.fixture(scope="session")
def strided_model(probe_model) -> PressureModel:
    """probe_model's weights, seeing every 3rd frame of a 43-frame window."""
    model = PressureModel.create(
        dataclasses.replace(probe_model.meta, model=ModelConfig(frames=15, frame_stride=3, width=8))
    )
    model.module.load_state_dict(probe_model.module.state_dict())
    return model


@pytest.fixture
def full_disk(tmp_path: Path):
    """A real small disk (tmpfs, 256 KiB) that fills up; skips where it cannot be mounted.

    Yields the mount point; writers tested on it must fail with a named error.
    """
    import subprocess

    mount = tmp_path / "small-disk"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


@pytest.fixture
def one_torch_thread():
    """The test machine is shared: one intra-op thread avoids spin-wait thrashing."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
