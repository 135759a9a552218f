"""Simulator mechanics, press trajectory, scale and configuration (no rendering)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from beadsight.config import REFERENCE_G_TO_N, ConfigError
from beadsight.sim import (
    PouchSimulator,
    Press,
    PressCycle,
    SimConfig,
    SimulatedScale,
    SimulatedSession,
)

DT = 1 / 30


def press_to(sim: PouchSimulator, xy, depth_mm: float, seconds: float = 1.5) -> float:
    """Hold the finger at ``depth_mm`` for ``seconds``; return the last force."""
    force = 0.0
    for _ in range(int(seconds / DT)):
        force = sim.step(DT, xy, depth_mm)
    return force


def release(sim: PouchSimulator, seconds: float = 1.5) -> None:
    for _ in range(int(seconds / DT)):
        sim.step(DT, (0.0, 0.0), -5.0)


# --- configuration -------------------------------------------------------------------
def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="n_beads"):
        SimConfig(n_beads=0)
    with pytest.raises(ConfigError, match="press_z_range_mm"):
        SimConfig(press_z_range_mm=(128.0, 127.0))
    with pytest.raises(ConfigError, match="jpeg_quality"):
        SimConfig(jpeg_quality=0)
    with pytest.raises(ConfigError, match="n_beads must be one of"):
        SimConfig.preset(90)


def test_config_round_trips_and_presets():
    cfg = SimConfig.preset(125, image_size_px=64)
    assert cfg.n_beads == 125 and cfg.image_size_px == 64
    assert SimConfig.from_dict(cfg.to_dict()) == cfg
    stiff = [SimConfig.preset(n).stiffness_ref_force_n for n in (75, 100, 125)]
    assert stiff == sorted(stiff) and len(set(stiff)) == 3
    assert cfg.geometry.image_size_px == 64 and cfg.geometry.finger_radius_mm == 6.25


def test_reference_depths_give_peaks_of_roughly_5_to_25_newtons():
    cfg = SimConfig()
    shallow, deep = cfg.depth_range_mm()  # press Z 128 and 127
    assert cfg.equilibrium_force_n(shallow) == pytest.approx(4.3, rel=0.05)
    assert 15 < cfg.equilibrium_force_n(deep) < 25
    session = SimulatedSession(
        dataclasses.replace(cfg, image_size_px=32), seed=3, presses=12, render=False
    )
    peaks = np.zeros(12)
    for f in session:
        peaks[f.press_index] = max(peaks[f.press_index], f.true_force_n)
    assert 3.5 < peaks.min() < 9 and 14 < peaks.max() < 28


# --- force ----------------------------------------------------------------------------
def test_no_force_without_contact():
    sim = PouchSimulator(SimConfig(), seed=0)
    assert press_to(sim, (0.0, 0.0), 0.0, 0.3) == 0.0
    assert press_to(sim, (0.0, 0.0), -2.0, 0.3) == 0.0


def test_force_rises_monotonically_with_depth():
    sim = PouchSimulator(SimConfig(), seed=0)
    depths = np.linspace(0.01, 2.2, 80)
    forces = [sim.step(0.05, (2.0, -3.0), d) for d in depths]
    assert np.all(np.diff(forces) > 0)
    assert forces[-1] > 20


def test_force_relaxes_during_the_dwell_and_is_stiffer_near_the_wall():
    cfg = SimConfig(press_stiffness_spread=0.0, packing_stiffness_gain=0.0)
    sim = PouchSimulator(cfg, seed=0)
    forces = [sim.step(DT, (0.0, 0.0), min(k * DT * 3.33, 1.5)) for k in range(60)]
    peak = int(np.argmax(forces))
    assert forces[-1] < 0.97 * forces[peak]  # stress relaxation while holding still
    edge = PouchSimulator(cfg, seed=0)
    assert press_to(edge, (13.75, 13.75), 1.5) > 1.15 * press_to(
        PouchSimulator(cfg, seed=0), (0.0, 0.0), 1.5
    )


# --- beads ------------------------------------------------------------------------------
def near_finger(sim: PouchSimulator, xy, reach_mm: float = 10.0) -> np.ndarray:
    rest = sim.bead_rest_positions_mm
    return np.linalg.norm(rest - np.asarray(xy), axis=1) < reach_mm


def test_bead_displacement_grows_with_force():
    xy = (-3.0, 4.0)
    results = []
    for depth in (0.6, 1.2, 1.8):
        sim = PouchSimulator(SimConfig(), seed=5)
        mask = near_finger(sim, xy)
        force = press_to(sim, xy, depth)
        disp = np.linalg.norm(sim.bead_positions_mm - sim.bead_rest_positions_mm, axis=1)
        results.append((force, disp[mask].mean()))
    forces, disps = zip(*results, strict=True)
    assert list(forces) == sorted(forces)
    assert list(disps) == sorted(disps) and disps[-1] > 2 * disps[0]


def test_motion_lags_the_finger():
    sim = PouchSimulator(SimConfig(), seed=1)
    mask = near_finger(sim, (0, 0))
    sim.step(DT, (0.0, 0.0), 1.5)
    first = sim.pouch.displacement_mm[: sim.config.n_beads][mask].mean()
    press_to(sim, (0.0, 0.0), 1.5, 1.0)
    settled = sim.pouch.displacement_mm[: sim.config.n_beads][mask].mean()
    assert first < 0.6 * settled


def test_beads_near_the_wall_move_less():
    cfg = SimConfig(push_gain_spread=0.0)
    sim = PouchSimulator(cfg, seed=2)
    rest = sim.bead_rest_positions_mm
    xy = np.array([13.75, 0.0])  # finger reaches the +X wall
    press_to(sim, xy, 1.5)
    disp = np.linalg.norm(sim.bead_positions_mm - rest, axis=1)
    rho = np.linalg.norm(rest - xy, axis=1)
    ring = (rho > 7) & (rho < 10)
    wall = ring & (rest[:, 0] > cfg.pouch_half_mm - 3.5)
    inner = ring & (rest[:, 0] < xy[0] - 4)
    assert wall.any() and inner.any()
    assert disp[wall].mean() < 0.6 * disp[inner].mean()


def test_beads_stay_inside_the_pouch():
    cfg = SimConfig.preset(125)
    sim = PouchSimulator(cfg, seed=4)
    rng = np.random.default_rng(0)
    for _ in range(6):
        xy = rng.uniform(-13.75, 13.75, 2)
        xy[rng.integers(2)] = rng.choice([-13.75, 13.75])  # at the edge of the press range
        press_to(sim, xy, 2.0, 1.0)
        view = sim.view()
        assert np.abs(view.xy_mm).max() <= cfg.pouch_half_mm
        release(sim, 0.5)
    assert np.abs(sim.bead_rest_positions_mm).max() <= cfg.pouch_half_mm


def test_each_press_leaves_a_new_arrangement():
    sim = PouchSimulator(SimConfig(), seed=6)
    release(sim, 0.5)
    before = sim.bead_rest_positions_mm
    xy = (5.0, 5.0)
    press_to(sim, xy, 1.6)
    release(sim, 3.0)
    after = sim.bead_rest_positions_mm
    moved = np.linalg.norm(after - before, axis=1)
    near = np.linalg.norm(before - np.array(xy), axis=1) < 10
    assert moved[near].mean() > 0.3  # mm: the beads that were pressed settled elsewhere
    assert moved[near].mean() > 2 * moved[~near].mean()
    # And they are at rest there: the lagged positions converge on the new arrangement.
    assert np.abs(sim.bead_positions_mm - after).max() < 0.2


def test_jitter_at_rest():
    sim = PouchSimulator(SimConfig(), seed=0)
    a = sim.view().xy_mm.copy()
    release(sim, 1.0)
    b = sim.view().xy_mm
    step = np.linalg.norm(a - b, axis=1)
    assert 0.005 < np.median(step) < 0.3


def test_same_seed_same_physics_different_seed_differs():
    def run(seed):
        sim = PouchSimulator(SimConfig(), seed=seed)
        forces = [sim.step(DT, (1.0, 2.0), 0.05 * k) for k in range(30)]
        return np.array(forces), sim.view().xy_mm

    f1, x1 = run(7)
    f2, x2 = run(7)
    f3, x3 = run(8)
    assert np.array_equal(f1, f2) and np.array_equal(x1, x2)
    assert not np.array_equal(x1, x3) and not np.array_equal(f1, f3)


def test_step_rejects_non_positive_dt():
    sim = PouchSimulator(SimConfig(), seed=0)
    with pytest.raises(ValueError, match="dt_s"):
        sim.step(0.0, (0, 0), 1.0)


# --- press trajectory ------------------------------------------------------------------
def test_press_cycle_follows_the_reference_pattern():
    cfg = SimConfig()
    press = Press(10.0, 0.0, 127.5)
    cycle = PressCycle(cfg, press, 0.0, (0.0, 0.0), 0)
    travel_s = 10.0 / (700 / 60)
    descend_s = (137.5 - 127.5) / (200 / 60)
    rise_s = (137.5 - 127.5) / (700 / 60)
    assert cycle.duration_s == pytest.approx(travel_s + descend_s + 1.0 + rise_s + cfg.pause_s)
    xy, z, phase = cycle.state_at(travel_s + descend_s + 0.5)
    assert phase == "dwell" and z == pytest.approx(127.5) and xy.tolist() == [10.0, 0.0]
    xy, z, phase = cycle.state_at(travel_s / 2)
    assert phase == "travel" and z == cfg.clear_z_mm and xy[0] == pytest.approx(5.0)
    down, up = cycle.contact_window_s()
    assert up - down == pytest.approx(1.5 / (200 / 60) + 1.0 + 1.5 / (700 / 60))
    assert cycle.commanded_xy_mm.tolist() == [10.0, 0.0]


# --- scale ------------------------------------------------------------------------------
def test_scale_reads_at_its_rate_with_noise_drift_and_two_decimals():
    cfg = SimConfig(scale_rate_hz=10.0, scale_noise_g=0.3)
    scale = SimulatedScale(cfg, seed=0)
    times, readings = [], []
    for k in range(6000):  # 200 s at 30 Hz, constant 1 N load
        t = 100.0 + k / 30
        g = scale.sample(t, 1.0)
        if g is not None:
            times.append(t)
            readings.append(g)
    readings = np.array(readings)
    assert len(readings) == pytest.approx(2000, abs=2)
    assert np.allclose(np.round(readings * 100), readings * 100)  # two decimals
    expected_g = 1.0 / REFERENCE_G_TO_N
    assert abs(readings.mean() - expected_g) < 3.0
    detrended = readings - np.convolve(readings, np.ones(25) / 25, mode="same")
    assert 0.15 < detrended[30:-30].std() < 0.5
    assert scale.sample(times[-1] + 0.001, 1.0) is None  # nothing between samples


def test_scale_averages_over_its_conversion_period():
    cfg = SimConfig(scale_rate_hz=10.0, scale_noise_g=0.0, scale_drift_g_per_sqrt_s=0.0)
    scale = SimulatedScale(cfg, seed=0)
    scale.sample(0.0, 0.0)
    t0 = scale.next_sample_s
    assert scale.sample(t0, 0.0) == 0.0
    # Load steps from 0 to 1 N half-way through the next conversion period.
    scale.sample(t0 + 0.05 - 1e-6, 0.0)
    scale.sample(t0 + 0.05, 1.0)
    g = scale.sample(t0 + 0.1, 1.0)
    assert g == pytest.approx(0.5 / REFERENCE_G_TO_N, rel=0.01)


def test_scale_refuses_time_going_backwards():
    scale = SimulatedScale(SimConfig(), seed=0)
    scale.sample(10.0, 0.0)
    with pytest.raises(ValueError, match="backwards"):
        scale.sample(9.0, 0.0)


# --- session ----------------------------------------------------------------------------
def test_session_frames_and_presses():
    cfg = SimConfig(image_size_px=32)
    session = SimulatedSession(cfg, seed=1, presses=2, render=False)
    frames = list(session)
    assert len(frames) == session.num_frames()
    t = np.array([f.timestamp_s for f in frames])
    assert np.all(np.diff(t) > 0) and t[0] >= cfg.start_time_s
    assert {f.press_index for f in frames} == {0, 1}
    phases = [f.phase for f in frames if f.press_index == 0]
    assert phases.index("descend") < phases.index("dwell") < phases.index("rise")
    readings = [r for f in frames for r in f.scale_readings]
    assert len(readings) == pytest.approx((t[-1] - t[0]) * cfg.scale_rate_hz, abs=2)
    for f in frames:
        assert np.array_equal(f.commanded_xy_mm, session.presses[f.press_index].xy_mm)
    # Loaded while the finger goes down and holds; on the way up the viscous pouch lags
    # behind the finger, so contact may end before the finger clears the surface.
    touching = [f for f in frames if f.finger_depth_mm > 0 and f.phase in ("descend", "dwell")]
    assert touching and all(f.true_force_n > 0 for f in touching)
    assert all(f.true_force_n == 0 for f in frames if f.finger_depth_mm <= 0)


@pytest.mark.timeout(60)
def test_session_takes_a_scale_sample_due_less_than_a_step_away():
    """A scale sample due < 1 us after the physics clock is a gap too short to step; the
    session used to wait for that sample forever (seed 700 hung at its 60th press). Here the
    frame rate puts a frame 0.5 us before the scale's second sample, in the first press."""
    cfg = dataclasses.replace(SimConfig(), frame_time_jitter_s=0.0)
    start = cfg.start_time_s
    # The scale's sample times depend on the seed and its rate, not on the frame rate.
    probe = SimulatedSession(cfg, seed=700, presses=1, render=False)
    due_s = [t for f in probe for t, _ in f.scale_readings][1] - start
    cfg = dataclasses.replace(cfg, fps=round(cfg.fps * due_s) / (due_s - 0.5e-6))
    session = SimulatedSession(cfg, seed=700, presses=1, render=False)
    frames = list(session)
    assert len(frames) == session.num_frames()
    readings = np.array([t for f in frames for t, _ in f.scale_readings])
    assert np.all(np.diff(readings) > 0)
    # The case was reached: a reading taken less than 1 us after a frame.
    after_frame = readings[:, None] - np.array([f.timestamp_s for f in frames])[None, :]
    assert np.any((after_frame > 0) & (after_frame < 1e-6))


def test_endless_session_starts_with_the_finite_sessions_presses():
    cfg = SimConfig(image_size_px=32)
    finite = SimulatedSession(cfg, seed=2, presses=2, render=False)
    endless = SimulatedSession(cfg, seed=2, render=False)
    a = [f.true_force_n for f in finite]
    b = [f.true_force_n for _, f in zip(range(len(a)), endless, strict=False)]
    assert a == b


def test_pouches_are_swapped_between_presses():
    cfg = SimConfig(image_size_px=32)

    def run():
        session = SimulatedSession(cfg, seed=3, presses=4, render=False, presses_per_pouch=2)
        arrangements = {}
        frames = []
        for f in session:
            frames.append((f.press_index, f.pouch_index, f.true_force_n))
            arrangements.setdefault(f.pouch_index, session.simulator.bead_rest_positions_mm)
        return frames, arrangements

    frames, arrangements = run()
    assert {(p, q) for p, q, _ in frames} == {(0, 0), (1, 0), (2, 1), (3, 1)}
    first, second = arrangements[0], arrangements[1]
    assert np.abs(first - second).mean() > 3.0  # a different pouch, not a settled one
    again, _ = run()
    assert again == frames
    with pytest.raises(ValueError, match="presses_per_pouch"):
        SimulatedSession(cfg, seed=3, presses=4, presses_per_pouch=0)
