"""The rest reference in use and sensor health, on the simulator.

The simulator is read by a perfect model (each reading is the simulator's true force), so
these tests see the rest and health logic alone; time is the simulator's frame time.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from beadsight.data.rest import REST_FRAMES, RestReference, average_rest
from beadsight.health.checkup import drift_timeline
from beadsight.health.flow import REST_PX, bead_motion
from beadsight.health.monitor import (
    SHIFT_STEP_MM,
    HealthMonitor,
    HealthSettings,
    deformation_mm,
    judge,
)
from beadsight.health.rest import REST_GUARD_FRAMES, SLOW_LOAD_MM
from beadsight.health.stillness import STILL_FRAMES
from beadsight.health.watch import SensorWatch
from beadsight.inference.predictor import PressureReading
from beadsight.sim.config import SimConfig
from beadsight.sim.press import Press
from beadsight.sim.scripted import steady_press
from beadsight.sim.session import SimulatedSession

SIZE = 64
FPS = 30.0
SENSOR_MM = SimConfig().sensor_size_mm


def truth(force_n: float, t_s: float) -> PressureReading:
    """A reading of ``force_n`` at ``t_s`` (the map itself does not matter here)."""
    empty = np.zeros((SIZE, SIZE), np.float32)
    contact = force_n >= 0.49
    return PressureReading(empty, force_n, np.full(2, np.nan), contact, empty > 0, 0, t_s, 0, 0, 0)


def session(config: SimConfig, presses, seconds: float):
    """(t_s, frame, true force) of a simulated session for ``seconds``."""
    for record in SimulatedSession(config, 0, presses):
        t = record.frame_index / FPS
        if t > seconds:
            return
        yield t, record.frame_rgb, float(record.true_force_n)


def watched(frames) -> tuple[list[RestReference], list[tuple[float, float]]]:
    """Run (t, frame, force) through a SensorWatch; the rest references it took and the
    (t, force) of every frame."""
    taken: list[RestReference] = []
    watch = SensorWatch(SENSOR_MM, on_rest=taken.append)
    seen = []
    for t, frame, force in frames:
        watch.process(frame, truth(force, t))
        seen.append((t, force))
    watch.close()
    return taken, seen


def test_a_steady_press_never_refreshes_the_rest():
    """The pouch rests 5 s, a press is held still for 20 s, then released: rest references
    are taken at start-up and again while unloaded, never while loaded (however still),
    nor in the frames just before the press touched."""
    config, presses = steady_press(20.0, config=SimConfig(image_size_px=SIZE))
    taken, seen = watched(session(config, presses, 40.0))
    t, force = np.array(seen).T
    loaded = t[force > 0.098]
    touch, release = loaded[0], loaded[-1]
    assert release - touch > 20.0  # the hold
    times = np.array([r.taken_at_s for r in taken])
    assert taken[0].origin == "start-up" and taken[0].taken_at_s < 2.0
    assert {r.origin for r in taken[1:]} == {"refreshed"}
    first_frames = times - (REST_FRAMES - 1) / FPS  # each rest image's oldest frame
    assert not ((times > touch - 0.1) & (first_frames < release + 0.1)).any(), times
    before, after = times[times < touch], times[times > release]
    assert len(before) >= 3 and len(after) >= 1  # about one per second of rest (the
    # scripted session ends 1.7 s after the release)
    assert np.all(np.diff(times) >= 1.0 - 1e-9)
    for r in taken:  # every image is the average of its frames
        assert r.frames == REST_FRAMES and r.image.shape == (SIZE, SIZE, 3)


@pytest.mark.parametrize("guard", [True, False])
def test_a_slow_load_the_model_misses_is_not_taken_for_the_rest(guard, monkeypatch):
    """A finger enters the pouch at 5 mm/min (a load growing by about 0.5 N/s) and is held;
    the model misses the load while it grows (reads 0 N) and reads it once held. The rest
    references are unloaded and still by the readings, but the beads moved locally: none
    is taken from a loaded pouch, and after the release the next one comes. Without the
    slow-load guard (the control), the growing load is taken into the rest."""
    from beadsight.health import rest

    if not guard:
        monkeypatch.setattr(rest, "SLOW_LOAD_MM", np.inf)
    config, presses = steady_press(
        5.0, ramp_feed_mm_min=5.0, rest_s=3.0, config=SimConfig(image_size_px=SIZE)
    )
    presses.append(Press(0.0, 0.0, config.clear_z_mm, dwell_s=8.0))  # then rests 8 s
    taken: list[RestReference] = []
    watch = SensorWatch(SENSOR_MM, on_rest=taken.append)
    force_at = {}
    for record in SimulatedSession(config, 0, presses):
        t, force = record.frame_index / FPS, float(record.true_force_n)
        force_at[round(t * FPS)] = force
        read = 0.0 if record.phase == "descend" else force  # the ramp is missed
        watch.process(record.frame_rgb, truth(read, t))
    watch.close()
    peak = max(force_at.values())
    assert peak > 5.0  # the held load
    loads = [  # the largest true force in each rest image's frames
        max(force_at[round(r.taken_at_s * FPS) - k] for k in range(REST_FRAMES)) for r in taken
    ]
    if not guard:  # the control: the ramp's load enters the rest image
        assert max(loads) > 1.0, loads
        return
    assert watch.tracker.refused >= 1
    assert max(loads) < 0.5, loads
    release = max(k for k, f in force_at.items() if f > 0) / FPS
    assert any(r.taken_at_s > release for r in taken)  # at rest again after the release


def test_an_unloaded_still_pouch_refreshes_it_and_a_moving_one_does_not():
    config = dataclasses.replace(SimConfig(image_size_px=SIZE), dwell_s=10.0)
    still = session(config, [Press(0.0, 0.0, config.clear_z_mm)], 5.0)
    taken, _ = watched(still)
    assert [r.origin for r in taken][:2] == ["start-up", "refreshed"] and len(taken) >= 4
    rng = np.random.default_rng(0)
    moving = ((k / FPS, rng.integers(0, 256, (SIZE, SIZE, 3), np.uint8), 0.0) for k in range(150))
    assert watched(moving)[0] == []


def test_a_stored_rest_waits_for_the_pouch_to_be_unloaded():
    """With a stored rest and the pouch loaded at start-up, the watch says so and keeps
    the stored rest until the pouch has been unloaded and still."""
    stored = RestReference(np.full((SIZE, SIZE, 3), 90, np.uint8), 8, 0.0, "file")
    taken = []
    watch = SensorWatch(SENSOR_MM, reference=stored, on_rest=taken.append)
    frame = np.full((SIZE, SIZE, 3), 100, np.uint8)
    for k in range(60):  # 2 s of a still, loaded pouch
        report = watch.process(frame, truth(4.0, k / FPS))
    assert taken == [] and watch.rest is stored
    assert report.state == "unknown" and report.message.startswith("loaded at start-up: 4.00 N")
    for k in range(60, 120):  # unloaded and still
        report = watch.process(frame, truth(0.0, k / FPS))
    watch.monitor.flush()
    assert taken and {r.origin for r in taken} == {"refreshed"} and watch.rest is taken[-1]
    assert taken[0].taken_at_s >= 60 / FPS + 14 / FPS  # after 15 unloaded readings
    np.testing.assert_array_equal(taken[0].image, frame)
    report = watch.report
    assert report.state == "drifting" and report.reference == "file"  # 90 -> 100: +11 %
    assert report.figures["brightness_change_pct"] == pytest.approx(100 / 90 * 100 - 100)
    watch.close()


def test_a_requested_rest_replaces_a_stale_one_that_reads_as_a_load():
    """A stale rest image (the pouch bumped) reads as a load that never ends, so the
    unloaded rule never refreshes it; asked for, the next still frames are taken whatever
    the readings and however recent the last rest reference, and only once."""
    taken = []
    watch = SensorWatch(SENSOR_MM, health=False, on_rest=taken.append)
    watch.tracker.refresh_s = 1e9  # no refresh but the one asked for
    frame = np.full((SIZE, SIZE, 3), 100, np.uint8)
    settle = 2 * STILL_FRAMES + 1 + REST_FRAMES + REST_GUARD_FRAMES  # still again, then one
    k = 0

    def frames(n: int, force_n: float = 4.0, still: bool = True) -> None:
        nonlocal k
        for _ in range(n):
            image = frame.copy()
            if not still:  # a bright bar sweeping across: motion
                image[:, (8 * k) % SIZE :][:, :16] = 230
            watch.process(image, truth(force_n, k / FPS))
            k += 1

    frames(settle, force_n=0.0)
    assert [r.origin for r in taken] == ["start-up"]
    frames(60)  # 2 s still under the phantom load: no new rest reference
    assert len(taken) == 1 and not watch.tracker.requested
    watch.request_rest()
    assert watch.tracker.requested
    frames(10, still=False)  # moving frames are never a rest image, asked for or not
    frames(settle)
    assert [r.origin for r in taken] == ["start-up", "requested"] and watch.rest is taken[1]
    np.testing.assert_array_equal(taken[1].image, frame)
    assert not watch.tracker.requested
    frames(90)  # the phantom load again: asked for once, taken once
    assert len(taken) == 2
    watch.close()


def test_no_false_alarm_on_a_clean_simulator_with_presses():
    first = drift_timeline(None, 60.0, image_size=SIZE, presses=True)
    assert set(first) == {"unknown", "ok"}, first


def test_a_camera_bump_between_presses_is_detected():
    first = drift_timeline("bump,bump_at_s=9", 25.0, image_size=SIZE, presses=True)
    assert "drifting" in first and 9.0 < first["drifting"] < 16.0, first


def test_no_drift_at_rest_stays_ok():
    first = drift_timeline(None, 8, image_size=SIZE)
    assert set(first) == {"unknown", "ok"} and first["ok"] < 1.5


def test_settling_beads_drift_then_need_recalibration():
    first = drift_timeline("settle,settle_tau_s=6", 16, image_size=SIZE)  # 1.2 mm, fast
    assert first["ok"] < first["drifting"] < first["recalibrate"] < 16


def test_light_change_drifts_then_needs_recalibration():
    first = drift_timeline("light,light_ramp_s=8", 14, image_size=SIZE)
    assert first["ok"] < first["drifting"] < first["recalibrate"] < 12


@pytest.mark.parametrize("bump_mm, state", [(1.0, "drifting"), (2.0, "recalibrate")])
def test_camera_bump_small_drifts_large_recalibrates(bump_mm, state):
    first = drift_timeline(f"bump,bump_at_s=3,bump_mm={bump_mm}", 6, image_size=SIZE)
    assert first["ok"] < 3 <= first[state] < 5
    assert set(first) == {"unknown", "ok", state}


def test_a_new_packing_after_a_press_is_not_drift_but_a_shift_across_it_is():
    """Rest states either side of a load: local bead motion is the press's new packing
    (not counted); a whole-image shift over SHIFT_STEP_MM is (the camera moved)."""
    rng = np.random.default_rng(3)
    beads = rng.integers(0, 256, (SIZE // 4, SIZE // 4), np.uint8)
    image = np.repeat(np.repeat(beads, 4, 0), 4, 1)[..., None].repeat(3, axis=2)
    repacked = image.copy()
    repacked[20:40, 20:40] = np.roll(image[20:40, 20:40], 2, axis=1)  # beads moved locally
    shifted = np.roll(repacked, 2, axis=1)  # 2 px = 1.3 mm: the camera moved
    monitor = HealthMonitor(SENSOR_MM)
    monitor.add(RestReference(image, 8, 0.0, "start-up"), False)
    assert monitor.add(RestReference(repacked, 8, 1.0, "refreshed"), True).state == "ok"
    report = monitor.add(RestReference(shifted, 8, 2.0, "refreshed"), True)
    assert report.figures["camera_shift_mm"] > max(1.0, SHIFT_STEP_MM), report.figures
    assert report.state == "drifting" and "camera_shift_mm" in report.message


def test_bead_motion_tells_a_local_push_from_a_drift():
    """A drift moves the whole image affinely (the beads creeping together, the camera
    shifted): little local motion. A finger pushes beads aside at one place: local."""
    rng = np.random.default_rng(3)
    beads = rng.integers(0, 256, (REST_PX // 4, REST_PX // 4), np.uint8)
    image = np.repeat(np.repeat(beads, 4, 0), 4, 1).astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    centre = (REST_PX - 1) / 2
    creep = cv2.getRotationMatrix2D((centre, centre), 0, 1.02)  # 0.4 mm at half the view
    crept = cv2.warpAffine(image, creep, (REST_PX, REST_PX), borderMode=cv2.BORDER_REFLECT)
    shifted = np.roll(image, 1, axis=1)  # 1 px = 0.64 mm
    pushed = image.copy()
    pushed[24:40, 24:40] = np.roll(image[24:40, 24:40], 1, axis=1)  # 10 mm of beads moved
    assert bead_motion(image, image, SENSOR_MM).local_mm < 0.01
    motion = bead_motion(image, crept, SENSOR_MM)
    assert deformation_mm(motion.deformation) > 0.3 and motion.local_mm < SLOW_LOAD_MM / 2
    motion = bead_motion(image, shifted, SENSOR_MM)
    assert motion.shift[0] == pytest.approx(SENSOR_MM / REST_PX, rel=0.05)
    assert motion.local_mm < SLOW_LOAD_MM / 2
    assert bead_motion(image, pushed, SENSOR_MM).local_mm > 3 * SLOW_LOAD_MM


def test_judge_takes_the_worst_figure_and_says_what_to_do():
    state, message = judge(
        {"bead_creep_mm": 0.1, "camera_shift_mm": 2.0}, HealthSettings().thresholds
    )
    assert state == "recalibrate" and "camera moved" in message
    assert judge({"bead_creep_mm": 0.35}, HealthSettings().thresholds)[0] == "drifting"


def test_rest_images_are_the_one_average():
    frames = np.random.default_rng(1).integers(0, 256, (REST_FRAMES, SIZE, SIZE, 3), np.uint8)
    taken: list[RestReference] = []
    watch = SensorWatch(SENSOR_MM, on_rest=taken.append, health=False)
    for k in range(40):  # the same frames over and over: still, unloaded
        watch.process(frames[k % REST_FRAMES], truth(0.0, k / FPS))
    assert len(taken) == 1 and watch.monitor is None
    np.testing.assert_array_equal(taken[0].image, average_rest(frames))


def test_creep_that_raised_the_state_stays_counted():
    """Creep while unloaded adds up over the stretches between presses: a stretch over
    0.1 mm counts, and a smaller one that takes the figure past the drifting threshold
    counts too (the state does not fall back once the next press starts a new stretch)."""
    import cv2

    rng = np.random.default_rng(4)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (SIZE, SIZE)).astype(np.float32), (0, 0), 1.5)

    def contracted(mm: float) -> RestReference:  # beads drawn mm inward at half the field
        scale = 1 - mm / (SENSOR_MM / 2)
        warp = cv2.getRotationMatrix2D(((SIZE - 1) / 2, (SIZE - 1) / 2), 0, scale)
        gray = cv2.warpAffine(texture, warp, (SIZE, SIZE), borderMode=cv2.BORDER_REFLECT)
        image = np.clip(gray, 0, 255).astype(np.uint8)[..., None].repeat(3, axis=2)
        return RestReference(image, 8, 0.0, "refreshed")

    monitor = HealthMonitor(SENSOR_MM)
    figures = []
    for mm, loaded in [(0, False), (0.25, False), (0.25, True), (0.34, False), (0.34, True)]:
        monitor.add(contracted(mm), loaded)
        figures.append(round(monitor.report.figures["bead_creep_mm"], 2))
    assert figures[1] == pytest.approx(0.25, abs=0.04)  # within the first stretch
    assert figures[3] == pytest.approx(0.34, abs=0.05) and monitor.report.state == "drifting"
    assert figures[4] == pytest.approx(figures[3], abs=0.02)  # kept across the press
