"""Simulator camera: sensor-space frames, raw fisheye frames, determinism."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from beadsight.geometry import mm_to_px
from beadsight.sim import PouchSimulator, SimConfig
from beadsight.sim.optics import render
from beadsight.sim.optics.fisheye import raw_to_sensor_maps
from beadsight.sim.optics.render import SensorRenderer
from beadsight.sim.pouch import PouchView

DT = 1 / 30
CLEAN = dict(noise_std=0.0, raw_noise_std=0.0, flicker=0.0, raw_jpeg_quality=None)


def pressed(config: SimConfig, seed: int, xy, depth_mm: float, seconds: float = 1.0):
    sim = PouchSimulator(config, seed)
    for _ in range(int(seconds / DT)):
        sim.step(DT, xy, depth_mm)
    return sim


@pytest.mark.parametrize("size", [64, 100, 256])
def test_render_shape_and_range(size):
    sim = PouchSimulator(SimConfig(image_size_px=size), seed=0)
    sim.step(DT, (0, 0), -1)
    frame = sim.render()
    assert frame.shape == (size, size, 3) and frame.dtype == np.uint8
    assert 20 < frame.mean() < 200 and frame.std() > 15  # beads on a dark background


def test_same_seed_same_frames_different_seed_differs():
    def frames(seed):
        sim = PouchSimulator(SimConfig(image_size_px=64), seed)
        out = []
        for k in range(10):
            sim.step(DT, (2.0, 1.0), 0.15 * k)
            out.append(sim.render())
        return np.stack(out)

    a, b, c = frames(3), frames(3), frames(4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a[0], a[1])  # noise and jitter: no two frames alike


def test_rendering_does_not_change_the_mechanics():
    cfg = SimConfig(image_size_px=64)
    watched, unwatched = PouchSimulator(cfg, 5), PouchSimulator(cfg, 5)
    for k in range(20):
        f1 = watched.step(DT, (0.0, -4.0), 0.1 * k)
        watched.render()
        f2 = unwatched.step(DT, (0.0, -4.0), 0.1 * k)
        assert f1 == f2
    assert np.array_equal(watched.view().xy_mm, unwatched.view().xy_mm)


def test_a_press_changes_the_image_near_the_finger_only():
    cfg = SimConfig(image_size_px=128, jitter_mm=0.0, drift_mm_per_sqrt_s=0.0, **CLEAN)
    xy = np.array([-6.0, 5.0])
    rest = pressed(cfg, 1, xy, -1.0).render().astype(float)
    load = pressed(cfg, 1, xy, 1.8).render().astype(float)
    diff = np.abs(load - rest).mean(axis=2)
    rows, cols = np.mgrid[0:128, 0:128] + 0.5
    centre = mm_to_px(xy, cfg.geometry)
    dist_mm = np.hypot(rows - centre[0], cols - centre[1]) * cfg.geometry.mm_per_px
    near, far = diff[dist_mm < 10].mean(), diff[dist_mm > 18].mean()
    assert near > 10 and near > 8 * far


def test_the_finger_itself_is_never_visible():
    # One bead, no bubbles: where no bead is, a pressed pouch looks exactly like a resting one.
    cfg = SimConfig(
        n_beads=1, n_bubbles=0, image_size_px=64, jitter_mm=0.0, drift_mm_per_sqrt_s=0.0, **CLEAN
    )
    rest_sim, load_sim = pressed(cfg, 2, (0, 0), -1.0), pressed(cfg, 2, (0, 0), 2.0)
    rest, load = rest_sim.render(), load_sim.render()
    rows, cols = np.mgrid[0:64, 0:64] + 0.5
    clear = np.ones((64, 64), bool)
    for sim in (rest_sim, load_sim):
        view = sim.view()
        rc = mm_to_px(view.xy_mm, cfg.geometry)
        for (r, c), radius in zip(rc, view.radius_mm, strict=True):
            reach = radius / cfg.geometry.mm_per_px + 2
            clear &= np.hypot(rows - r, cols - c) > reach
    assert clear.sum() > 3000
    assert np.array_equal(rest[clear], load[clear])


def test_flattening_shows_depth_without_steps():
    # Sprites exist for a few flatness levels; each bead's own threshold between them
    # makes the beads together follow the flatness (the depth) in fine steps.
    cfg = SimConfig(image_size_px=64, **CLEAN)
    k = cfg.n_beads + cfg.n_bubbles
    side = math.ceil(math.sqrt(k))
    grid = np.linspace(-17.0, 17.0, side)
    xy = np.stack(np.meshgrid(grid, grid), axis=-1).reshape(-1, 2)[:k]
    renderer = SensorRenderer(cfg, 64, 0, np.random.default_rng(0))
    frames = set()
    for flatness in np.linspace(0.3, 0.6, 31):  # 1.8 to 3.6 of the 7 sprite levels
        view = PouchView(
            xy_mm=xy,
            radius_mm=np.full(k, 2.0),
            flatness=np.full(k, flatness),
            tint=np.zeros(k, np.int64),
            index=np.arange(k),
        )
        frames.add(renderer.render(view).tobytes())
    assert len(frames) >= 28  # rounding to the nearest level would give 3


def test_jpeg_option_compresses_frames():
    plain = PouchSimulator(SimConfig(image_size_px=128), seed=0)
    jpeg = PouchSimulator(SimConfig(image_size_px=128, jpeg_quality=75), seed=0)
    a, b = plain.render().astype(float), jpeg.render().astype(float)
    assert 0.5 < np.abs(a - b).mean() < 10  # chroma subsampling and blocks, noise removed


def test_raw_maps_invert_the_reference_preprocessing():
    """Geometry alone: the reference crop's source pixels map back to where they belong."""
    from beadsight.preprocess import REFERENCE_INPUT_HW, reference_maps

    size = 750  # sensor-space pixels == reference crop pixels
    map_rows, map_cols, inside = raw_to_sensor_maps(size)
    src_r, src_c = reference_maps(REFERENCE_INPUT_HW, truncate=True)
    src_r, src_c = src_r[1:-1:7, 1:-1:7].astype(int), src_c[1:-1:7, 1:-1:7].astype(int)
    assert inside[src_r, src_c].all()
    want_r, want_c = np.mgrid[1:749:7, 1:749:7]
    err = np.hypot(map_rows[src_r, src_c] - want_r, map_cols[src_r, src_c] - want_c)
    # Truncation to whole raw pixels: up to one raw pixel, ~2.4 crop pixels at the corners.
    assert err.mean() < 0.5 and err.max() < 2.0
    assert not inside[0, 0] and inside[512, 640]


def test_raw_frames_come_back_through_the_reference_preprocessing():
    from beadsight.preprocess import Preprocessor

    cfg = SimConfig(image_size_px=256, **CLEAN)
    sim = pressed(cfg, 3, (4.0, -6.0), 1.6, seconds=0.5)
    raw = sim.render_raw()
    assert raw.shape == (1024, 1280, 3) and raw.dtype == np.uint8
    assert raw[0, 0].max() == 0  # outside the fisheye's image circle
    back = Preprocessor.reference()(raw)
    sensor = sim.render()
    assert np.corrcoef(back.ravel(), sensor.ravel())[0, 1] > 0.97
    assert np.abs(back.astype(float) - sensor.astype(float)).mean() < 6
    g1, g2 = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float32) for x in (back, sensor))
    (dx, dy), _ = cv2.phaseCorrelate(g1, g2)
    assert abs(dx) < 0.3 and abs(dy) < 0.3  # pixels at 256: no shift, flip or rotation


def test_raw_frames_have_sensor_noise_and_jpeg():
    sim = PouchSimulator(SimConfig(raw_render_px=256), seed=0)
    a, b = sim.render_raw(), sim.render_raw()
    diff = a.astype(float) - b.astype(float)
    assert 2 < diff[300:700, 400:900].std() < 12  # frame-to-frame noise


def test_documentation_figure(tmp_path):
    from beadsight.sim.figure import simulator_figure

    path = simulator_figure(tmp_path / "fig.png", seed=0, image_size=64)
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] > 1000


def test_session_can_yield_raw_frames():
    import itertools

    from beadsight.sim import SimulatedSession

    cfg = SimConfig(image_size_px=32, raw_render_px=256)
    frames = list(itertools.islice(SimulatedSession(cfg, seed=0, raw=True), 2))
    assert all(f.raw_bgr.shape == (1024, 1280, 3) for f in frames)
    assert frames[0].frame_rgb.shape == (32, 32, 3)


def test_sprites_are_shared_by_look_and_kept_within_the_byte_budget(monkeypatch):
    """Renderers of one look and size share their sprites (and draw the same frames as a
    renderer with none cached); past the budget the look used longest ago goes first, then
    the oldest quarter of the look being drawn."""
    made = []
    make = SensorRenderer._make_sprite
    monkeypatch.setattr(SensorRenderer, "_make_sprite", lambda r, k: made.append(k) or make(r, k))
    config = SimConfig(image_size_px=64, flicker=0.0)
    monkeypatch.setattr(render, "SPRITES", render.SpriteCache())  # the process's stays intact
    frame = pressed(config, 4, (1.0, 0.0), 1.5).render()
    assert made and len(render.SPRITES.sprites((config, 64))) == len(made)
    first = len(made)
    assert np.array_equal(pressed(config, 4, (1.0, 0.0), 1.5).render(), frame)
    assert len(made) == first  # the second renderer made none
    monkeypatch.setattr(render, "SPRITES", render.SpriteCache())
    assert np.array_equal(pressed(config, 4, (1.0, 0.0), 1.5).render(), frame)
    assert len(made) == 2 * first

    one = (np.zeros((10, 10, 3), np.float32), np.zeros((10, 10, 3), np.float32))  # 2400 B
    sprites = render.SpriteCache(max_bytes=10 * 2400)
    a, b = (SimConfig(image_size_px=32), 32), (SimConfig(image_size_px=48), 48)
    for key in range(6):
        sprites.add(a, key, one)
    assert len(sprites.sprites(b)) == 0  # b is now the look used last
    for key in range(5):
        sprites.add(b, key, one)
    assert len(sprites.sprites(b)) == 5 and len(sprites.sprites(a)) == 0  # a went first
    for key in range(5, 11):  # b alone over the budget: its oldest quarter goes
        sprites.add(b, key, one)
    kept = sprites.sprites(b)
    assert sorted(kept) == list(range(2, 11))  # 11 over a budget of 10: 2 (a quarter) went
