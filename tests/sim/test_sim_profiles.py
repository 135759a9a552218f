"""Press profiles: long holds, slow ramps, depth changes while held, re-rest after release."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from beadsight.cli import main
from beadsight.data.dataset import open_dataset
from beadsight.data.presses import segment_presses
from beadsight.errors import ConfigError
from beadsight.sim import SimConfig, SimulatedSession, simulate_dataset
from beadsight.sim.dataset import ScaleLog
from beadsight.sim.press import (
    MIXED_KINDS,
    PROFILES,
    RAMP_START_ABOVE_SURFACE_MM,
    HoldMove,
    Press,
    PressCycle,
)

SETTLE_S = 3.0  # five relaxation times (0.6 s): the viscoelastic overshoot is gone
HOLD_FORCE_TOL = 0.005  # a settled hold's true force stays within 0.5 % of its level
STILL_RATIO = 1.25  # a settled hold's frame-to-frame change is at most this x the rest's
BEAD_STILL_MM_PER_S = 0.06  # a held bead's place (1 s mean) moves less than this per second
BEAD_CHATTER_MM = 0.1  # 99th percentile of a held bead's frame-to-frame motion, mm


def run(session):
    """Frames of ``session`` with the beads' lagged positions at each frame."""
    frames, beads = [], []
    for f in session:
        frames.append(f)
        beads.append(session.simulator.bead_positions_mm)
    return frames, np.stack(beads)


def frame_change(frames) -> np.ndarray:
    """(N-1,) mean absolute change between consecutive frames, 0..255."""
    img = np.stack([f.frame_rgb for f in frames]).astype(np.float32)
    return np.abs(np.diff(img, axis=0)).mean(axis=(1, 2, 3))


def kind(press: Press) -> str:
    if press.is_reference:
        return "reference"
    if press.hold_moves:
        return "changing"
    if press.ramp_feed_mm_min is not None:
        return "ramp"
    return "long_hold" if press.dwell_s >= 60 else "hold"


# --- the reference profile is today's --------------------------------------------------
def test_reference_profile_is_unchanged():
    """Numbers recorded from the simulator before profiles existed (commit a13ee68)."""
    frames = list(SimulatedSession(SimConfig(), 5, 3, render=False))
    assert len(frames) == 579
    assert sum(f.true_force_n for f in frames) == pytest.approx(1202.2492227372159, rel=1e-12)
    grams = sum(g for f in frames for _, g in f.scale_readings)
    assert grams == pytest.approx(40859.28, rel=1e-12)
    assert frames[-1].timestamp_s == 1700000019.2670174
    again = list(SimulatedSession(SimConfig(), 5, 3, render=False, profile="reference"))
    assert [f.true_force_n for f in again] == [f.true_force_n for f in frames]


def test_mixed_presses_are_the_reference_presses_with_profiles():
    cfg = SimConfig()
    ref = SimulatedSession(cfg, 3, 50, render=False).presses
    mixed = SimulatedSession(cfg, 3, 50, render=False, profile="mixed").presses
    assert [(p.x_mm, p.y_mm, p.z_mm) for p in ref] == [(p.x_mm, p.y_mm, p.z_mm) for p in mixed]
    assert {kind(p) for p in mixed} == {k for k, _ in MIXED_KINDS}
    for a, b in zip(ref, mixed, strict=True):
        assert b == a if b.is_reference else b != a


def test_mixed_proportions_and_length():
    cfg = SimConfig()
    n = 2000
    ref = SimulatedSession(cfg, 0, n, render=False)
    mixed = SimulatedSession(cfg, 0, n, render=False, profile="mixed")
    counts = {k: 0 for k, _ in MIXED_KINDS}
    for p in mixed.presses:
        counts[kind(p)] += 1
        if kind(p) == "long_hold":
            assert p.dwell_s >= 60
    for k, prob in MIXED_KINDS:
        assert counts[k] / n == pytest.approx(prob, abs=0.03)
    # neither the reference presses nor the long holds dominate the frames
    ratio = mixed.duration_s() / ref.duration_s()
    assert 2.0 < ratio < 4.0


# --- determinism ------------------------------------------------------------------------
def test_mixed_is_deterministic_per_seed():
    cfg = SimConfig(image_size_px=32)

    def first(seed, count=400, render=True):
        s = SimulatedSession(cfg, seed, 6, profile="mixed", render=render)
        return s.presses, [f for _, f in zip(range(count), s, strict=False)]

    # Seed 12's first 400 frames hold a reference press and a changing-while-held one. The
    # other seed's frames are never compared: physics only (rendering never changes it).
    (pa, fa), (pb, fb), (pc, fc) = first(12), first(12), first(11, render=False)
    assert {f.press_index for f in fa} == {0, 1} and pa[1].hold_moves
    assert pa == pb and pa != pc
    assert all(np.array_equal(a.frame_rgb, b.frame_rgb) for a, b in zip(fa, fb, strict=True))
    assert [f.true_force_n for f in fa] == [f.true_force_n for f in fb]
    assert [f.true_force_n for f in fa] != [f.true_force_n for f in fc]


def test_endless_mixed_session_starts_with_the_finite_sessions_presses():
    cfg = SimConfig(image_size_px=32)
    finite = SimulatedSession(cfg, 4, 3, render=False, profile="mixed")
    endless = SimulatedSession(cfg, 4, render=False, profile="mixed")
    a = [f.true_force_n for f in finite]
    b = [f.true_force_n for _, f in zip(range(len(a)), endless, strict=False)]
    assert a == b


# --- the motion of one press -------------------------------------------------------------
def test_slow_ramp_descends_its_last_part_at_the_ramp_feed():
    cfg = SimConfig()
    press = Press(0.0, 0.0, 127.5, dwell_s=2.0, ramp_feed_mm_min=30.0, release_feed_mm_min=40.0)
    cycle = PressCycle(cfg, press, 0.0, (0.0, 0.0), 0)
    ramp_z = cfg.surface_z_mm + RAMP_START_ABOVE_SURFACE_MM
    approach_s = (cfg.clear_z_mm - ramp_z) / (cfg.descend_feed_mm_min / 60)
    ramp_s = (ramp_z - 127.5) / (30 / 60)
    release_s = (ramp_z - 127.5) / (40 / 60)
    up_s = (cfg.clear_z_mm - ramp_z) / (cfg.rise_feed_mm_min / 60)
    assert cycle.duration_s == pytest.approx(approach_s + ramp_s + 2.0 + release_s + up_s + 0.5)
    down, up = cycle.contact_window_s()
    assert up - down == pytest.approx(1.5 / 0.5 + 2.0 + 1.5 / (40 / 60))
    _, z, phase = cycle.state_at(approach_s + ramp_s / 2)
    assert phase == "descend" and z == pytest.approx((ramp_z + 127.5) / 2)


def test_hold_moves_change_depth_while_held():
    cfg = SimConfig()
    moves = (HoldMove(127.2, 200.0, 1.0), HoldMove(127.6, 3.0, 1.0))
    cycle = PressCycle(cfg, Press(0.0, 0.0, 127.5, dwell_s=1.0, hold_moves=moves), 0.0, (0, 0), 0)
    bottom = (cfg.clear_z_mm - 127.5) / (cfg.descend_feed_mm_min / 60)
    step_s, drift_s = 0.3 / (200 / 60), 0.4 / (3 / 60)
    t = bottom + 1.0 + step_s + 0.5
    assert cycle.state_at(t)[1:] == (pytest.approx(127.2), "dwell")
    t = bottom + 1.0 + step_s + 1.0 + drift_s / 2
    assert cycle.state_at(t)[1:] == (pytest.approx(127.4), "adjust")
    down, up = cycle.contact_window_s()
    assert up - down == pytest.approx(
        1.5 / (200 / 60) + 1.0 + step_s + 1.0 + drift_s + 1.0 + 1.4 / (700 / 60)
    )


# --- the physics of a hold and a release ------------------------------------------------
@pytest.fixture(scope="module")
def long_hold():
    """Rest, then a 60 s press held at 1.5 mm, then rise and rest (32 px frames)."""
    cfg = SimConfig(image_size_px=32)
    press = Press(2.0, -3.0, cfg.surface_z_mm - 1.5, dwell_s=60.0)
    rest = Press(2.0, -3.0, cfg.clear_z_mm - 0.01, dwell_s=3.0)  # never touches: 3 s unloaded
    session = SimulatedSession(cfg, 21, [press, rest])
    frames, beads = run(session)
    return cfg, frames, beads


def test_a_long_hold_is_steady_in_force_frames_and_beads(long_hold):
    cfg, frames, beads = long_hold
    t = np.array([f.timestamp_s for f in frames]) - cfg.start_time_s
    dwell = np.array([f.phase == "dwell" and f.press_index == 0 for f in frames])
    t0, t1 = t[dwell][0], t[dwell][-1]
    assert t1 - t0 == pytest.approx(60.0, abs=0.1)
    held = dwell & (t >= t0 + SETTLE_S)
    force = np.array([f.true_force_n for f in frames])
    level = force[held].mean()
    assert 5 < level < 25
    assert np.abs(force[held] / level - 1).max() < HOLD_FORCE_TOL
    # the label (the scale) reads the same steady force
    scale = np.array([f.scale_force_n for f in frames])
    assert scale[held].mean() == pytest.approx(level, rel=0.02)
    # the frames are as still as at rest (noise, flicker and jitter only)
    change = frame_change(frames)
    rest = t[1:] < 1.5  # before the finger comes down
    assert change[held[1:]].mean() < STILL_RATIO * change[rest].mean()
    # and the beads stay where they are: second by second, no bead moves more than a hair
    k = np.flatnonzero(held)
    per_s = int(cfg.fps)
    seconds = beads[k[: len(k) // per_s * per_s]].reshape(-1, per_s, *beads.shape[1:])
    mean_xy = seconds.mean(axis=1)  # (S, n_beads, 2) each bead's place in each second
    assert np.abs(np.diff(mean_xy, axis=0)).max() < BEAD_STILL_MM_PER_S
    assert np.abs(mean_xy[-1] - mean_xy[0]).max() < 0.15  # the slow drift of the packing
    # Under load, the overlap push and the viscous pull of a few beads alternate from frame
    # to frame (a numerical chatter of the mechanics, as in every reference dwell): bounded.
    chatter = np.linalg.norm(np.diff(beads[k], axis=0), axis=2)
    assert np.percentile(chatter, 99) < BEAD_CHATTER_MM


def test_after_release_the_force_is_zero_and_the_pouch_settles_to_a_new_rest(long_hold):
    cfg, frames, beads = long_hold
    t = np.array([f.timestamp_s for f in frames]) - cfg.start_time_s
    force = np.array([f.true_force_n for f in frames])
    # the force is zero once the finger has left (the viscous pouch may let go earlier)
    off = next(i for i, f in enumerate(frames) if f.phase == "rise" and f.finger_depth_mm <= 0)
    assert np.all(force[off:] == 0) and force[off - 30] > 5
    settled = t >= t[off] + 2.0
    change = frame_change(frames)
    rest = t[1:] < 1.5
    assert change[settled[1:]].mean() < STILL_RATIO * change[rest].mean()
    k = np.flatnonzero(settled)
    assert np.abs(beads[k[-1]] - beads[k[0]]).max() < 0.1  # still
    assert np.abs(beads[k[0]] - beads[0]).max() > 0.1  # a new packing, not the old one


def test_depth_changes_while_held_change_the_force():
    cfg = SimConfig()
    z = cfg.surface_z_mm - 1.2
    moves = (
        HoldMove(z - 0.4, 200.0, 4.0),  # step deeper
        HoldMove(z - 0.1, 200.0, 4.0),  # step back up
        HoldMove(z + 0.3, 4.0, 4.0),  # slow drift up (4.5 s)
    )
    press = Press(0.0, 0.0, z, dwell_s=4.0, hold_moves=moves)
    session = SimulatedSession(cfg, 2, [press], render=False)
    frames = list(session)
    cycle = PressCycle(cfg, press, 0.0, (0, 0), 0)
    ends = np.cumsum([d for d in np.diff(cycle._times)])  # segment end times (s)
    dwell_ends = [ends[i] for i, p in enumerate(cycle._phases) if p == "dwell"]
    t = np.array([f.timestamp_s for f in frames]) - cfg.start_time_s
    force = np.array([f.true_force_n for f in frames])
    levels = [force[np.searchsorted(t, e) - 2] for e in dwell_ends]
    depths = [1.2, 1.6, 1.3, 0.9]
    for i in range(len(depths) - 1):
        assert (levels[i + 1] > levels[i]) == (depths[i + 1] > depths[i])
    # deeper holds press harder, by the pouch's force law (same press, same stiffness)
    ratio = np.array(levels) / np.array([cfg.equilibrium_force_n(d) for d in depths])
    assert np.ptp(ratio) / ratio.mean() < 0.02
    # the drift changes the force smoothly while it runs: no frame-to-frame jump
    drift = np.array([f.phase == "adjust" for f in frames]) & (t > dwell_ends[2])
    assert np.abs(np.diff(force[drift])).max() < 0.1


# --- datasets and the press segmentation --------------------------------------------------
def test_segmentation_finds_every_mixed_press():
    cfg = SimConfig()
    # Seed 272's 6 presses hold all five kinds, in few frames (a single long hold).
    session = SimulatedSession(cfg, 272, 6, render=False, profile="mixed")
    assert {kind(p) for p in session.presses} == {k for k, _ in MIXED_KINDS}
    log, t, pos, index = ScaleLog(), [], [], []
    for f in session:
        log.add(f.scale_readings)
        t.append(f.timestamp_s)
        pos.append(f.commanded_xy_mm)
        index.append(f.press_index)
    force, valid = log.at(np.array(t))
    _, _, presses = segment_presses(force, valid, np.array(pos))
    assert [index[a] for a, _ in presses] == list(range(6))
    assert all(index[b - 1] == index[a] for a, b in presses)


@pytest.mark.slow
def test_mixed_dataset_through_the_cli_with_workers(tmp_path):
    out = tmp_path / "mixed.h5"
    args = ["simulate", "--out", str(out), "--presses", "2", "--pouches", "2", "--workers", "2"]
    # seed 1: shards of 187 and 564 frames (seed 3 drew a 2,435-frame hold: 3x the CPU)
    args += ["--profile", "mixed", "--image-size", "32", "--seed", "1", "--no-progress"]
    assert main(args) == 0
    with open_dataset(out) as ds:
        assert ds.num_presses == 2
        assert ds.provenance["simulator"]["profile"] == "mixed"
        assert len(ds) / 2 > 1.2 * 200  # longer than reference presses


# --- bad input ------------------------------------------------------------------------------
def test_bad_profile_names_the_valid_ones(tmp_path):
    for call in (
        lambda: SimulatedSession(SimConfig(), 0, 2, profile="steady"),
        lambda: simulate_dataset(tmp_path / "x.h5", 2, profile="Mixed", progress=False),
    ):
        with pytest.raises(ConfigError, match="profile must be one of") as info:
            call()
        assert all(name in str(info.value) for name in PROFILES)
    with pytest.raises(ConfigError, match="carries its own profile"):
        SimulatedSession(SimConfig(), 0, [Press(0.0, 0.0, 127.5)], profile="mixed")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"dwell_s": -1.0}, "Press.dwell_s must be a number >= 0"),
        ({"ramp_feed_mm_min": 0.0}, "Press.ramp_feed_mm_min must be a number > 0"),
        ({"hold_moves": ((127.0, 20.0),)}, "Press.hold_moves must be HoldMove objects"),
    ],
)
def test_bad_press_profile(change, message):
    with pytest.raises(ConfigError, match=message):
        dataclasses.replace(Press(0.0, 0.0, 127.5), **change)
