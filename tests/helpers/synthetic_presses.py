"""Synthetic finger presses: force ramps at random positions and the frames they darken.

Shared by the dataset fixtures (conftest.py), the live tests (helpers/live.py) and the
reference-file tests; a normal module, so any test folder can import it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.geometry import mm_to_px


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


def write_synthetic_dataset(
    path: Path,
    presses: int = 6,
    frames_per_press: int = 40,
    image_size: int = 64,
    seed: int = 0,
    fps: float = 30.0,
) -> Path:
    """A dataset file of synthetic presses (all frames valid, one press after another)."""
    geometry = SensorGeometry(image_size_px=image_size)
    rng = np.random.default_rng(seed)
    force, position = make_press_arrays(presses, frames_per_press, geometry, rng)
    frames = synthetic_press_frames(force, position, geometry, rng)
    n = len(force)
    t = 1.7e9 + np.arange(n) / fps
    with DatasetWriter(path, geometry, fps=fps, provenance={"source": "test-fixture"}) as w:
        w.append(frames, force, position, np.ones(n, bool), t)
    return path
