"""The range of real builds (sim/variety.py): seeded, split cleanly, and every factor shows.

Each factor is set to the low and the high end of its training range, everything
else held at the reference build, and the rendered frames (or, for the pouch's
stiffness, the force) are measured for the change that factor must make.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from beadsight.cli import main
from beadsight.data.dataset import open_dataset
from beadsight.errors import ConfigError
from beadsight.sim import PouchSimulator, SimConfig, SimulatedSession, simulate_dataset
from beadsight.sim.optics.camera import camera_is_reference, view_maps
from beadsight.sim.optics.light import colour_temperature_rgb
from beadsight.sim.variety import (
    FACTOR_NAMES,
    FACTORS,
    PouchDistribution,
    build_config,
    factor_table,
    sample_pouch,
)

DT = 1 / 30
SIZE = 128
# The reference build, seen without noise or flicker, so one factor's change is all there is.
BASE = SimConfig(image_size_px=SIZE, noise_std=0.0, flicker=0.0)
BY_NAME = {f.name: f for f in FACTORS}


def render(config: SimConfig, seed: int = 0, depth_mm: float = -1.0, frames: int = 1):
    """The last of ``frames`` frames of a pouch, the finger at the centre (not touching at -1)."""
    sim = PouchSimulator(config, seed)
    for _ in range(frames):
        sim.step(DT, (0.0, 0.0), depth_mm)
        frame = sim.render()
    return frame.astype(np.float64)


def ends(name: str, base: SimConfig = BASE, **kw) -> tuple[np.ndarray, np.ndarray]:
    """Frames with factor ``name`` at the low and the high end of its training range."""
    lo, hi = BY_NAME[name].train
    return render(build_config({name: lo}, base), **kw), render(
        build_config({name: hi}, base), **kw
    )


def bead_count(frame: np.ndarray) -> int:
    """Beads seen: local brightness maxima of the smoothed image (one per bead at 128 px)."""
    grey = cv2.cvtColor(frame.astype(np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)
    smooth = cv2.GaussianBlur(grey, (0, 0), 2.0)
    peaks = smooth >= cv2.dilate(smooth, np.ones((5, 5), np.uint8))
    return int((peaks & (smooth > 60)).sum())


def detail(frame: np.ndarray) -> float:
    """RMS of the image minus its blurred self: fine detail (noise, sharp edges)."""
    grey = frame.mean(axis=2).astype(np.float32)
    return float(np.sqrt(((grey - cv2.GaussianBlur(grey, (0, 0), 1.0)) ** 2).mean()))


# --- the distribution --------------------------------------------------------------
def test_sampling_is_seeded_and_reproducible():
    def draw(seed, split="train"):
        rng = np.random.default_rng(seed)
        return [sample_pouch(rng, split) for _ in range(4)]

    a, b, c = draw(7), draw(7), draw(8)
    assert [s.factors for s in a] == [s.factors for s in b]
    assert [s.config for s in a] == [s.config for s in b]
    assert a[0].factors != c[0].factors
    assert len({s.config.n_beads for s in a}) > 1  # four different builds
    assert set(a[0].factors) == set(FACTOR_NAMES)
    # A build's config survives the provenance's JSON (the demo rebuilds pouches from it).
    assert all(
        SimConfig.from_dict(json.loads(json.dumps(s.config.to_dict()))) == s.config for s in a
    )


def test_heldout_and_training_ranges_do_not_overlap():
    heldout = [f for f in FACTORS if f.heldout]
    assert {f.name for f in heldout} >= {"n_beads", "led_colour_temperature_k", "led_intensity"}
    for f in heldout:
        t_lo, t_hi = f.train
        for lo, hi in f.heldout:
            assert lo <= hi and (hi < t_lo or lo > t_hi), f.name
    # Drawn values keep to their split's ranges, and held-out values never reach training's.
    rng = np.random.default_rng(0)
    for split in ("train", "heldout"):
        for _ in range(300):
            values = PouchDistribution().sample(rng, split).factors
            for f in FACTORS:
                v = values[f.name]
                assert any(lo <= v <= hi for lo, hi in f.ranges(split)), (split, f.name, v)
                assert not f.integer or v == int(v)
                if split == "heldout" and f.heldout:
                    assert not f.train[0] <= v <= f.train[1], (f.name, v)
    # Both ends of a held-out bead count range are reached.
    counts = {PouchDistribution().sample(rng, "heldout").config.n_beads for _ in range(400)}
    assert {60, 70, 130, 140} <= counts and counts <= set(range(60, 71)) | set(range(130, 141))


def test_heldout_build_differs_from_its_training_twin_only_in_heldout_factors():
    train = sample_pouch(np.random.default_rng(3), "train")
    held = sample_pouch(np.random.default_rng(3), "heldout")
    differ = {n for n in FACTOR_NAMES if train.factors[n] != held.factors[n]}
    assert differ == {f.name for f in FACTORS if f.heldout}


def test_base_config_keeps_rig_and_image_size():
    base = SimConfig(image_size_px=48, fps=25.0, press_range_mm=10.0)
    config = sample_pouch(np.random.default_rng(1), "train", base).config
    assert (config.image_size_px, config.fps, config.press_range_mm) == (48, 25.0, 10.0)
    assert config.geometry == base.geometry
    assert not camera_is_reference(config)


def test_bad_split_and_bad_fields_name_what_was_expected():
    with pytest.raises(ConfigError, match="variety split must be one of"):
        sample_pouch(np.random.default_rng(0), "test")
    with pytest.raises(ConfigError, match="camera_tilt_deg"):
        SimConfig(camera_tilt_deg=(30.0, 0.0))
    with pytest.raises(ConfigError, match="white_balance_rgb"):
        SimConfig(white_balance_rgb=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="colour temperature"):
        colour_temperature_rgb(500.0)


def test_reference_camera_is_the_identity_and_offset_shifts_by_the_offset():
    cols, rows = view_maps(BASE, SIZE)
    grid = np.arange(SIZE, dtype=np.float64)
    assert np.abs(cols - grid[None, :]).max() < 1e-9 and np.abs(rows - grid[:, None]).max() < 1e-9
    cols, rows = view_maps(BASE.replace(camera_offset_mm=(1.0, -0.5)), SIZE)
    px_per_mm = SIZE / BASE.sensor_size_mm
    # Printer +X is image -column: the camera moved +X sees the pouch 1 mm further -column.
    assert np.allclose(cols - grid[None, :], -1.0 * px_per_mm, atol=1e-6)
    assert np.allclose(rows - grid[:, None], 0.5 * px_per_mm, atol=1e-6)


# --- every factor changes what the camera sees ---------------------------------------
def test_pouch_factors_show():
    lo, hi = ends("n_beads")
    assert bead_count(lo) == pytest.approx(71, abs=3) and bead_count(hi) == pytest.approx(
        129, abs=3
    )
    small, big = ends("bead_diameter_mm")
    assert (big > 60).mean() > (small > 60).mean() + 0.1  # bigger beads cover more
    uniform, mixed = ends("bead_diameter_spread_mm")
    assert np.abs(uniform - mixed).mean() > 5
    pale, strong = ends("tint_strength")
    assert strong.std(axis=2).mean() > 1.5 * pale.std(axis=2).mean()  # more colourful

    def hue_spread(frame):
        bright = frame[frame.mean(axis=2) > 80]
        return np.std(bright[:, 0] - bright[:, 2])

    one, six = ends("tint_count")
    assert hue_spread(six) > 1.5 * hue_spread(one)
    none, many = ends("n_bubbles")
    assert np.abs(none - many).mean() > 1.0
    # Bubbles float behind the beads: show them through the gaps of a sparse pouch.
    small, large = ends("bubble_max_diameter_mm", base=BASE.replace(n_beads=60, n_bubbles=12))
    assert (np.abs(small - large).max(axis=2) > 10).mean() > 0.005


def test_pouch_stiffness_factors_change_the_force():
    def force(values):
        sim = PouchSimulator(build_config(values, BASE), 0)
        for _ in range(30):
            sim.step(DT, (0.0, 0.0), 1.5)
        return sim.force_n

    lo, hi = BY_NAME["stiffness_scale"].train
    assert force({"stiffness_scale": hi}) / force({"stiffness_scale": lo}) == pytest.approx(
        hi / lo, rel=0.02
    )
    lo, hi = BY_NAME["stiffness_exponent"].train
    assert force({"stiffness_exponent": hi}) > 1.2 * force({"stiffness_exponent": lo})


def test_light_factors_show():
    dim, bright = ends("led_intensity")
    assert bright.mean() > 1.3 * dim.mean()
    warm, cold = ends("led_colour_temperature_k")
    ratio = lambda f: f[..., 0].mean() / f[..., 2].mean()  # noqa: E731
    assert ratio(warm) > 1.3 * ratio(cold)
    flat, dark_corners = ends("vignetting")

    def corner_ratio(f):
        q = SIZE // 8
        corners = np.concatenate([f[:q, :q], f[:q, -q:], f[-q:, :q], f[-q:, -q:]])
        return corners.mean() / f[3 * q : 5 * q, 3 * q : 5 * q].mean()

    assert corner_ratio(dark_corners) < 0.8 * corner_ratio(flat)
    for name in ("led_offset_mm", "led_height_mm", "led_rotation_deg"):
        a, b = ends(name)
        assert np.abs(a - b).mean() > 2.0, name
    low, high = ends("ambient_light")
    assert high.mean() > 1.05 * low.mean()


def test_camera_factors_show():
    under, over = ends("exposure_gain")
    assert over.mean() > 1.2 * under.mean()
    for name, channel in (("white_balance_red", 0), ("white_balance_blue", 2)):
        low, high = ends(name)
        assert high[..., channel].mean() > 1.1 * low[..., channel].mean(), name
        assert abs(high[..., 1].mean() - low[..., 1].mean()) < 0.5, name  # green untouched
    px_per_mm = SIZE / BASE.sensor_size_mm
    for name, axis in (
        ("camera_offset_x_mm", 0),
        ("camera_offset_y_mm", 1),
        ("crop_offset_x_mm", 0),
        ("crop_offset_y_mm", 1),
    ):
        low, high = ends(name)
        (dx, dy), _ = cv2.phaseCorrelate(low.mean(axis=2), high.mean(axis=2))
        lo, hi = BY_NAME[name].train
        shift = (dx, dy)[axis]
        # The image moves by the offset (printer +X/+Y is image -column/-row).
        assert abs(shift) == pytest.approx((hi - lo) * px_per_mm, rel=0.2), (name, dx, dy)
    for name in (
        "camera_tilt_rows_deg",
        "camera_tilt_cols_deg",
        "camera_roll_deg",
        "lens_focal_error",
        "lens_distortion_k",
        "crop_scale_error",
    ):
        low, high = ends(name)
        assert np.abs(low - high).mean() > 4.0, name


def test_image_factors_show():
    reference = render(BASE)  # the same pouch without noise: the difference is the noise
    for value in BY_NAME["noise_std"].train:
        noise = render(build_config({"noise_std": value}, BASE)) - reference
        assert noise.std() == pytest.approx(value, rel=0.15)
    sharp, blurred = ends("defocus_sigma_mm")
    assert detail(blurred) < 0.8 * detail(sharp)
    low, high = ends("jpeg_quality")
    assert np.abs(low - reference).mean() > 1.3 * np.abs(high - reference).mean()

    def brightness_wobble(flicker):
        sim = PouchSimulator(BASE.replace(flicker=flicker), 0)
        means = []
        for _ in range(12):
            sim.step(DT, (0.0, 0.0), -1.0)
            means.append(sim.render().mean())
        return np.std(means)

    assert brightness_wobble(BY_NAME["flicker"].train[1]) > 3 * brightness_wobble(0.0) + 0.1

    # Motion blur shows while beads move (the finger descending), hardly at rest.
    def last_frame(blur, depth):
        sim = PouchSimulator(BASE.replace(motion_blur_fraction=blur), 0)
        for k in range(12):
            sim.step(DT, (0.0, 0.0), depth(k))
            frame = sim.render()
        c = slice(SIZE // 4, 3 * SIZE // 4)  # around the finger
        return frame[c, c].astype(np.float64)

    def smear(depth):
        return np.abs(last_frame(0.4, depth) - last_frame(0.0, depth)).mean()

    moving, still = smear(lambda k: -0.5 + 0.2 * k), smear(lambda k: -1.0)
    assert moving > 3 * still and moving > 1.0


def test_docs_list_every_factor():
    doc = (Path(__file__).parents[2] / "docs" / "simulator.md").read_text()
    assert factor_table() in doc  # the documented ranges are the code's
    assert all(f"| `{name}` |" in factor_table() for name in FACTOR_NAMES)


# --- sessions and datasets ----------------------------------------------------------
def test_variety_session_swaps_builds_and_keeps_the_plain_session_unchanged():
    cfg = SimConfig(image_size_px=32)
    # The plain session is only the reference clock and plan: physics only (rendering
    # never changes them).
    plain = list(SimulatedSession(cfg, seed=2, presses=2, presses_per_pouch=1, render=False))
    again = SimulatedSession(cfg, seed=2, presses=2, presses_per_pouch=1, variety="train")
    frames = list(again)
    # The variety stream is a new one: plan, clock and scale are those of the plain session.
    assert [f.timestamp_s for f in frames] == [f.timestamp_s for f in plain]
    assert [tuple(f.commanded_xy_mm) for f in frames] == [tuple(f.commanded_xy_mm) for f in plain]
    assert again.pouch_config(0) != again.pouch_config(1)
    assert again.simulator.config == again.pouch_config(1)
    assert again.pouch_config(0).n_beads == again.pouch_build(0).factors["n_beads"]
    with pytest.raises(ConfigError, match="no variety"):
        SimulatedSession(cfg, seed=2, presses=1).pouch_build(0)


def test_variety_dataset_records_its_builds(tmp_path):
    # 10 fps: a third of the frames; what is checked here is the provenance, not the frames.
    out = simulate_dataset(
        tmp_path / "v.h5",
        presses=3,
        seed=4,
        image_size=32,
        fps=10.0,
        pouches=3,
        variety="heldout",
        progress=False,
    )
    with open_dataset(out) as ds:
        record = ds.provenance["simulator"]["variety"]
    assert record["split"] == "heldout" and record["factor_names"] == list(FACTOR_NAMES)
    beads = [row[FACTOR_NAMES.index("n_beads")] for row in record["pouch_factors"]]
    assert len(beads) == 3 and all(60 <= b <= 70 or 130 <= b <= 140 for b in beads)
    session = SimulatedSession(
        SimConfig(image_size_px=32, fps=10.0), 4, 3, presses_per_pouch=1, variety="heldout"
    )
    assert beads == [session.pouch_config(i).n_beads for i in range(3)]


def test_simulate_cli_variety(tmp_path, capsys):
    out = tmp_path / "t.h5"
    argv = ["simulate", "--out", str(out), "--presses", "2", "--pouches", "2", "--seed", "1"]
    small = ["--image-size", "32", "--fps", "10"]  # a third of the frames: none is read
    assert main([*argv, *small, "--variety", "train", "--no-progress"]) == 0
    with open_dataset(out) as ds:
        assert ds.provenance["simulator"]["variety"]["split"] == "train"
        assert ds.num_presses == 2 and ds.image_size == 32
    with pytest.raises(SystemExit):
        main([*argv, "--variety", "test"])
    assert "invalid choice" in capsys.readouterr().err


def test_colour_temperature_runs_warm_to_cold():
    rgb = [colour_temperature_rgb(k) for k in (2800, 4000, 5000, 6500)]
    blue_over_red = [b / r for r, _, b in rgb]
    assert blue_over_red == sorted(blue_over_red)
    assert all(math.isclose(max(c), 1.0) for c in rgb)


def test_training_on_a_variety_dataset_resumes_where_it_stopped(tmp_path):
    """A base-model run spans sessions: stopped and resumed, it ends where an
    uninterrupted run ends, on the same multi-build dataset."""
    import torch

    from beadsight.checkpoint import read_checkpoint_file

    data = simulate_dataset(
        tmp_path / "v.h5",
        presses=3,
        seed=6,
        image_size=32,
        fps=10.0,
        pouches=3,
        variety="train",
        progress=False,
    )
    small = ["--width", "2", "--batch-size", "4", "--threads", "1", "--no-progress"]
    small += ["--device", "cpu", "--loader", "host", "--num-workers", "0"]
    # Short windows and every 8th validation window: the claim is the resume, not the fit.
    small += ["--frames", "5", "--val-stride", "8"]

    def train(out, steps, *extra):
        args = ["train", "--data", str(data), "--out", str(out), "--steps", str(steps)]
        assert main([*args, *small, *extra]) == 0
        return read_checkpoint_file(out / "last.pt")

    whole = train(tmp_path / "whole", 4)
    train(tmp_path / "parts", 2)
    resumed = train(tmp_path / "parts", 4, "--resume")
    assert resumed["step"] == whole["step"] == 4
    assert whole["state_dict"].keys() == resumed["state_dict"].keys()
    for name, tensor in whole["state_dict"].items():
        assert torch.equal(tensor, resumed["state_dict"][name]), name
