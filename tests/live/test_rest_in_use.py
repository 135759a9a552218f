"""The rest reference in a live sensor: taken from still frames at start-up (no reading
before it), used by every reading, refreshed while the pouch is unloaded and still; a
stored rest file serves from the first frame; ``beadsight health --save-rest`` writes a
file ``live --rest`` reads."""

from __future__ import annotations

import dataclasses
import logging
import threading

import numpy as np
import pytest
import torch
from helpers.live import TINY, TORCH, StatusLog, wait_until

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig
from beadsight.data.rest import REST_FRAMES, with_rest
from beadsight.devices.virtual.camera import SimCamera
from beadsight.errors import ConfigError
from beadsight.health.checkup import run_checkup
from beadsight.live.sensor import WAITING_FOR_REST, LiveSensor
from beadsight.sim.config import SimConfig
from beadsight.sim.press import Press

pytestmark = pytest.mark.usefixtures("no_thread_leaks")


@pytest.fixture(scope="module")
def quiet_model() -> PressureModel:
    """An untrained rest-referenced model whose readings are about 0 N (output scale
    1e-6 kPa): to it, the pouch is always unloaded."""
    torch.manual_seed(2)
    meta = CheckpointMeta(
        model=ModelConfig(frames=4, frame_stride=2, width=8, rest_input=True),
        geometry=TINY,
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=1e-6,
    )
    return PressureModel.create(meta)


def resting_camera(seconds: float) -> SimCamera:
    """The simulated pouch at rest for ``seconds`` (64 px), one frame per read."""
    config = dataclasses.replace(SimConfig(), dwell_s=seconds)
    rest = [Press(0.0, 0.0, config.clear_z_mm)]
    return SimCamera(64, config=config, presses=rest, realtime=False, queue_frames=1)


def run(model, settings, seconds: float):
    """Run a live sensor on the resting pouch; each update with the rest image and the
    window the predictor had for it, and the status changes."""
    sensor = LiveSensor(model, resting_camera(seconds), settings).open()
    # frames come as fast as they are read, stamped with the host's time: refresh the rest
    # whenever the tracker has one (every 20 frames at rest), not once a host second
    sensor.watch.tracker.refresh_s = 0.0
    predictor, seen, used = sensor.predictor, [], []
    update = predictor.update

    def update_with(frame_rgb, t_s):  # the rest in use when the model runs
        used.append(predictor.rest)
        return update(frame_rgb, t_s)

    predictor.update = update_with
    sensor.on_update(lambda u: seen.append((u, used[-1], predictor.window_frames().copy())))
    log = StatusLog()
    sensor.add_listener(log)
    with sensor:
        sensor.wait(60)
    assert sensor.error is None
    return sensor, seen, log


class _Lines(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


@pytest.fixture(scope="module")
def rested(quiet_model):
    """run() of 4 s on the resting pouch with fp32 torch (about 100 readings: 5 rests, 3
    needed) and the INFO lines it logged; the tests that take it only read it."""
    root, lines = logging.getLogger(), _Lines()
    level, before = root.level, set(threading.enumerate())
    root.setLevel(logging.INFO)
    root.addHandler(lines)
    try:
        sensor, seen, log = run(quiet_model, TORCH, 4.0)
    finally:
        root.removeHandler(lines)
        root.setLevel(level)

    def started() -> list:  # no_thread_leaks checks each test, after this: check the run here
        return [t for t in threading.enumerate() if t not in before and t.is_alive()]

    wait_until(lambda: not started(), 10, "threads of the run to end")
    return sensor, seen, log, lines.lines


def test_the_rest_is_taken_at_start_up_and_refreshed_while_unloaded(quiet_model, rested):
    sensor, seen, log, lines = rested
    assert ("warming_up", WAITING_FOR_REST) in log.changes  # no reading before the rest
    first = seen[0][0].source_index
    assert first >= 30, first  # still frames seen, plus the guard frames after them
    said = [line for line in lines if "taken at start-up" in line]
    assert len(said) == 1 and "keep the pouch unloaded" in said[0]
    # every reading is the model's against the rest in use (the model run once, batched)
    expected = quiet_model.predict(np.stack([with_rest(rest, w) for _, rest, w in seen]))
    got = np.stack([update.reading.pressure_kpa for update, _, _ in seen])
    np.testing.assert_allclose(got, expected, atol=1e-9, rtol=1e-4)
    rests = {id(rest) for _, rest, _ in seen}
    assert len(rests) >= 3  # refreshed while unloaded and still
    np.testing.assert_array_equal(sensor.predictor.rest, sensor.watch.rest.image)  # the newest
    assert seen[-1][0].health.state == "ok"


def test_a_stored_rest_serves_from_the_first_frame(quiet_model, rested, tmp_path):
    sensor = rested[0]
    path = tmp_path / "rest.npz"
    sensor.watch.rest.save(path)
    stored = dataclasses.replace(TORCH, rest_file=str(path))
    _, again, log = run(quiet_model, stored, 1.0)
    assert again[0][0].source_index == quiet_model.span - 1  # a reading per window at once
    np.testing.assert_array_equal(again[0][1], sensor.watch.rest.image)
    assert WAITING_FOR_REST not in [m for _, m in log.changes]


def test_retake_rest_takes_the_next_still_frames_and_the_readings_use_them(quiet_model):
    sensor = LiveSensor(quiet_model, resting_camera(20.0), TORCH).open()
    sensor.watch.tracker.refresh_s = 1e9  # no rest reference but the start-up one and ours
    asked, used, done = [], [], threading.Event()

    def on_update(update) -> None:
        if not asked:  # the first reading: the start-up rest is in use
            asked.append(sensor.rest)
            sensor.retake_rest()
            assert sensor.rest_requested
        elif sensor.rest.origin == "requested" and not used:
            used.append(sensor.predictor.rest.copy())
            done.set()

    sensor.on_update(on_update)
    with sensor:
        assert done.wait(60), "no requested rest reference taken"
    assert sensor.error is None and asked[0].origin == "start-up"
    assert used and not sensor.rest_requested
    np.testing.assert_array_equal(used[0], sensor.rest.image)  # the model reads against it
    assert sensor.rest.taken_at_s > asked[0].taken_at_s


def test_retake_rest_without_a_rest_reference_is_refused_by_name(tiny_model):
    settings = dataclasses.replace(TORCH, health=False)
    with LiveSensor(tiny_model, resting_camera(1.0), settings) as sensor:
        with pytest.raises(ConfigError, match="no rest input and health is off"):
            sensor.retake_rest()


def test_health_save_rest_writes_what_live_rest_reads(quiet_model, tmp_path):
    path = tmp_path / "saved.npz"
    sensor = LiveSensor(quiet_model, resting_camera(4.0), TORCH)
    report = run_checkup(sensor, 30.0, save_rest=path)
    assert report.state == "ok" and path.is_file()
    stored = dataclasses.replace(TORCH, rest_file=str(path))
    _, seen, _ = run(quiet_model, stored, 1.0)
    assert seen and seen[0][0].source_index == quiet_model.span - 1


def test_bench_live_runs_a_rest_referenced_model(rest_model):
    """``beadsight bench live``: the predictor takes its rest from the first frames, and
    its parity windows carry that rest image."""
    from beadsight.live.bench import bench_live

    frames = np.random.default_rng(0).integers(0, 256, (40, 64, 64, 3), np.uint8)
    result = bench_live(rest_model, "torch", "fp32", 40, None, source_frames=frames)
    assert result.throughput.readings >= 40 - REST_FRAMES and result.max_abs_err_pct < 1e-3
