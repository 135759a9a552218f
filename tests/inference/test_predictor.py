"""PressurePredictor: ring buffer, dropped-frame policy, readings, input validation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from beadsight import PressurePredictor, PressureReading
from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig
from beadsight.geometry import (
    centre_of_pressure_mm,
    contact_area_mm2,
    disk_maps,
    disk_pressure_kpa,
    total_force_n,
)
from beadsight.inference.predictor import DEFAULT_FPS, PredictorSettings
from beadsight.inference.runtimes import Backend, TorchBackend
from beadsight.metrics import otsu_thresholds

FPS = DEFAULT_FPS
T = 15


def _frames(n: int, size: int = 64, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(n, size, size, 3), dtype=np.uint8)


def _predictor(model: PressureModel, **settings) -> PressurePredictor:
    return PressurePredictor.from_checkpoint(
        model, "torch", "fp32", settings=PredictorSettings(**settings)
    )


class FixedMapBackend(Backend):
    """A backend returning a known map, to check the reductions of a reading exactly."""

    name = "fixed"

    def __init__(self, model: PressureModel, pressure_kpa: np.ndarray):
        super().__init__(model)
        self.pressure_kpa = pressure_kpa.astype(np.float32)

    def _run(self, window: np.ndarray) -> np.ndarray:
        return self.pressure_kpa[None].copy()


# --- ring buffer -------------------------------------------------------------------
def test_none_until_window_full_then_matches_model_predict(tiny_model):
    frames = _frames(T + 5)
    predictor = _predictor(tiny_model)
    for k in range(T - 1):
        assert predictor.update(frames[k], k / FPS) is None
        assert not predictor.ready
    for k in range(T - 1, T + 5):
        reading = predictor.update(frames[k], k / FPS)
        assert isinstance(reading, PressureReading)
        expected = tiny_model.predict(frames[k - T + 1 : k + 1])  # oldest first
        np.testing.assert_allclose(reading.pressure_kpa, expected, atol=1e-5, rtol=0)
        np.testing.assert_array_equal(predictor.window_frames(), frames[k - T + 1 : k + 1])
        np.testing.assert_allclose(predictor.window_timestamps(), np.arange(k - T + 1, k + 1) / FPS)
        assert reading.frame_index == k
        assert reading.timestamp_s == pytest.approx(k / FPS)


def test_window_order_matters(tiny_model):
    """The newest frame must be last: a reversed window gives a different map."""
    frames = _frames(T)
    predictor = _predictor(tiny_model)
    for k in range(T):
        reading = predictor.update(frames[k], k / FPS)
    reversed_map = tiny_model.predict(frames[::-1].copy())
    assert np.abs(reading.pressure_kpa - reversed_map).max() > 1e-3


def test_update_does_not_keep_a_reference_to_the_caller_frame(tiny_model):
    frames = _frames(T)
    predictor = _predictor(tiny_model)
    frame = frames[0].copy()
    predictor.update(frame, 0.0)
    frame[:] = 0  # the caller reuses its buffer
    np.testing.assert_array_equal(predictor.window_frames()[-1], frames[0])


def test_reset_clears_window_and_counters(tiny_model):
    frames = _frames(T + 1)
    predictor = _predictor(tiny_model)
    for k in range(T):
        predictor.update(frames[k], k / FPS)
    assert predictor.ready
    predictor.reset()
    assert not predictor.ready
    assert predictor.update(frames[T], 100.0) is None  # earlier timestamps are fine now
    assert predictor.frame_index == 0
    assert predictor.dropped_frames == 0


# --- dropped frames ----------------------------------------------------------------
def _fill(predictor: PressurePredictor, frames: np.ndarray, t0: float = 0.0) -> float:
    for k, frame in enumerate(frames):
        predictor.update(frame, t0 + k / FPS)
    return t0 + (len(frames) - 1) / FPS


def test_small_gap_is_counted_and_window_continues(tiny_model):
    frames = _frames(T + 1)
    predictor = _predictor(tiny_model)  # default max_gap_frames=3, on_gap="reset"
    last = _fill(predictor, frames[:T])
    reading = predictor.update(frames[T], last + 3 / FPS)  # 2 frames missing
    assert reading is not None
    assert reading.dropped_frames == 2
    np.testing.assert_array_equal(predictor.window_frames(), frames[1 : T + 1])


def test_jitter_is_not_a_drop(tiny_model):
    frames = _frames(T + 1)
    predictor = _predictor(tiny_model)
    last = _fill(predictor, frames[:T])
    reading = predictor.update(frames[T], last + 1.4 / FPS)
    assert reading.dropped_frames == 0


def test_large_gap_resets_by_default(tiny_model):
    frames = _frames(2 * T)
    predictor = _predictor(tiny_model, max_gap_frames=3)
    last = _fill(predictor, frames[:T])
    t = last + 10 / FPS  # 9 frames missing > 3
    assert predictor.update(frames[T], t) is None
    assert predictor.gap_resets == 1
    assert predictor.dropped_frames == 9
    for k in range(1, T - 1):
        assert predictor.update(frames[T + k], t + k / FPS) is None
    reading = predictor.update(frames[2 * T - 1], t + (T - 1) / FPS)
    assert reading is not None and reading.dropped_frames == 9
    expected = tiny_model.predict(frames[T : 2 * T])
    np.testing.assert_allclose(reading.pressure_kpa, expected, atol=1e-5, rtol=0)


def test_large_gap_hold_repeats_last_frame(tiny_model):
    frames = _frames(T + 1)
    predictor = _predictor(tiny_model, max_gap_frames=1, on_gap="hold")
    last = _fill(predictor, frames[:T])
    reading = predictor.update(frames[T], last + 5 / FPS)  # 4 missing
    assert reading is not None and reading.dropped_frames == 4
    window = predictor.window_frames()
    np.testing.assert_array_equal(window[-1], frames[T])
    for k in range(2, 6):  # the 4 held copies of the frame before the gap
        np.testing.assert_array_equal(window[-k], frames[T - 1])
    np.testing.assert_array_equal(window[: T - 5], frames[5:T])
    expected = tiny_model.predict(window.copy())
    np.testing.assert_allclose(reading.pressure_kpa, expected, atol=1e-5, rtol=0)


def test_large_gap_ignore_counts_only(tiny_model):
    frames = _frames(T + 1)
    predictor = _predictor(tiny_model, max_gap_frames=0, on_gap="ignore")
    last = _fill(predictor, frames[:T])
    reading = predictor.update(frames[T], last + 30 / FPS)
    assert reading is not None and reading.dropped_frames == 29
    np.testing.assert_array_equal(predictor.window_frames(), frames[1 : T + 1])


def test_fps_comes_from_checkpoint_provenance(tiny_model):
    meta = dataclasses.replace(tiny_model.meta, provenance={"fps": 10.0})
    model = PressureModel(tiny_model.module, meta)
    predictor = _predictor(model, fps=60.0)  # the checkpoint's rate wins
    assert predictor.fps == 10.0
    frames = _frames(T)
    for k in range(T):
        reading = predictor.update(frames[k], k / 10.0)
    assert reading is not None and reading.dropped_frames == 0
    assert _predictor(tiny_model, fps=60.0).fps == 60.0  # no provenance: the argument


@pytest.mark.parametrize("bad", [0.5 / FPS, 0.0, -1.0])
def test_timestamps_must_increase(tiny_model, bad):
    frames = _frames(2)
    predictor = _predictor(tiny_model)
    predictor.update(frames[0], 0.5 / FPS)
    with pytest.raises(ValueError, match="timestamp_s must increase"):
        predictor.update(frames[1], bad)


def test_bad_policy_arguments(tiny_model):
    with pytest.raises(ValueError, match="on_gap"):
        _predictor(tiny_model, on_gap="skip")
    with pytest.raises(ValueError, match="max_gap_frames"):
        _predictor(tiny_model, max_gap_frames=-1)
    with pytest.raises(ValueError, match="contact_method"):
        _predictor(tiny_model, contact_method="fancy")


# --- readings ----------------------------------------------------------------------
def test_reading_fields_follow_the_map(tiny_model):
    frames = _frames(T)
    predictor = _predictor(tiny_model)
    for k in range(T):
        reading = predictor.update(frames[k], 1000.0 + k / FPS)
    g = tiny_model.geometry
    p = reading.pressure_kpa
    assert p.shape == (64, 64) and p.dtype == np.float32
    assert reading.force_n == pytest.approx(float(total_force_n(p, g)), rel=1e-6)
    np.testing.assert_allclose(reading.cop_mm, centre_of_pressure_mm(p, g), atol=1e-9)
    np.testing.assert_array_equal(reading.contact_mask, p >= predictor.contact_threshold_kpa)
    assert reading.contact_area_mm2 == pytest.approx(
        float(contact_area_mm2(reading.contact_mask, g))
    )
    assert reading.has_contact == (reading.force_n >= predictor.contact_force_n)
    assert reading.timestamp_s == pytest.approx(1000.0 + (T - 1) / FPS)
    assert 0 < reading.latency_s < 5
    with pytest.raises(dataclasses.FrozenInstanceError):
        reading.force_n = 0.0
    with pytest.raises(ValueError):
        reading.pressure_kpa[0, 0] = 1.0  # read-only


def test_reading_of_a_known_disk(tiny_model):
    g = tiny_model.geometry
    force, xy = 12.0, np.array([4.0, -3.0])
    disk = disk_maps(np.array([force]), xy[None], g)[0]
    predictor = PressurePredictor(tiny_model, backend=FixedMapBackend(tiny_model, disk))
    for k, frame in enumerate(_frames(T)):
        reading = predictor.update(frame, k / FPS)
    assert reading.force_n == pytest.approx(force, rel=0.01)
    np.testing.assert_allclose(reading.cop_mm, xy, atol=0.05)
    assert reading.has_contact
    np.testing.assert_array_equal(reading.contact_mask, disk >= predictor.contact_threshold_kpa)
    disk_area = np.pi * g.finger_radius_mm**2  # + the anti-aliased rim, 1/2 px wide at 64 px
    assert reading.contact_area_mm2 == pytest.approx(disk_area, rel=0.15)
    # the default threshold is the release force's pressure over the finger disk
    assert predictor.contact_threshold_kpa == pytest.approx(
        float(disk_pressure_kpa(10 * 9.81e-3, g))
    )


def test_empty_map_has_nan_cop_and_no_contact(tiny_model):
    predictor = PressurePredictor(
        tiny_model, backend=FixedMapBackend(tiny_model, np.zeros((64, 64)))
    )
    for k, frame in enumerate(_frames(T)):
        reading = predictor.update(frame, k / FPS)
    assert reading.force_n == 0.0
    assert np.isnan(reading.cop_mm).all()
    assert not reading.has_contact and not reading.contact_mask.any()
    assert reading.contact_area_mm2 == 0.0


def test_otsu_contact_mask_splits_two_levels(tiny_model):
    pressure = np.zeros((64, 64), np.float32)
    pressure[10:20, 10:20] = 50.0
    pressure[30:40, 30:40] = 5.0  # weaker region: below Otsu's split of {5, 50}
    predictor = PressurePredictor(
        tiny_model,
        backend=FixedMapBackend(tiny_model, pressure),
        settings=PredictorSettings(contact_method="otsu"),
    )
    for k, frame in enumerate(_frames(T)):
        reading = predictor.update(frame, k / FPS)
    np.testing.assert_array_equal(reading.contact_mask, pressure == 50.0)
    assert 5.0 < otsu_thresholds(np.array([[5.0] * 100 + [50.0] * 100]))[0] <= 50.0


# --- input validation --------------------------------------------------------------
def test_frame_of_wrong_resolution_names_both_sizes(tiny_model):
    predictor = _predictor(tiny_model)
    with pytest.raises(ValueError, match=r"640x480 px.*64x64"):  # width x height
        predictor.update(np.zeros((480, 640, 3), np.uint8), 0.0)


@pytest.mark.parametrize(
    "frame, message",
    [
        (np.zeros((64, 64), np.uint8), r"\(64, 64, 3\) uint8"),
        (np.zeros((64, 64, 4), np.uint8), r"\(64, 64, 3\) uint8"),
        (np.zeros((64, 64, 3), np.float32), "uint8"),
        ([[0, 1, 2]], r"\(64, 64, 3\) uint8"),
    ],
)
def test_bad_frames_are_refused(tiny_model, frame, message):
    predictor = _predictor(tiny_model)
    with pytest.raises(ValueError, match=message):
        predictor.update(frame, 0.0)
    assert predictor.frame_index == -1  # nothing was buffered


def test_model_from_checkpoint_path(tiny_model, tmp_path):
    path = tiny_model.save(tmp_path / "tiny.pt")
    predictor = PressurePredictor.from_checkpoint(path, backend="torch")
    assert isinstance(predictor.backend, TorchBackend)
    assert predictor.model.source == str(path)
    frames = _frames(T)
    for k in range(T):
        reading = predictor.update(frames[k], k / FPS)
    np.testing.assert_allclose(reading.pressure_kpa, tiny_model.predict(frames), atol=1e-5)


def test_predictor_with_other_frame_count(tiny_model):
    meta = CheckpointMeta(
        model=ModelConfig(frames=4, width=8),
        geometry=tiny_model.geometry,
        pixel_mean=[100.0] * 3,
        pixel_std=[50.0] * 3,
        channel_order="BGR",
        output_scale_kpa=3.0,
    )
    model = PressureModel.create(meta)
    predictor = _predictor(model)
    frames = _frames(6)
    readings = [predictor.update(f, k / FPS) for k, f in enumerate(frames)]
    assert [r is None for r in readings] == [True, True, True, False, False, False]
    np.testing.assert_allclose(readings[-1].pressure_kpa, model.predict(frames[2:]), atol=1e-5)


def test_predictor_with_frame_stride(tiny_model):
    meta = dataclasses.replace(
        tiny_model.meta, model=ModelConfig(frames=4, frame_stride=2, width=8)
    )
    model = PressureModel.create(meta)
    predictor = _predictor(model)
    frames = _frames(9)
    readings = [predictor.update(f, k / FPS) for k, f in enumerate(frames)]
    assert [r is None for r in readings] == [True] * 6 + [False] * 3  # span 7
    np.testing.assert_array_equal(predictor.window_frames(), frames[2:])
    np.testing.assert_allclose(readings[-1].pressure_kpa, model.predict(frames[2:]), atol=1e-5)


# --- construction ------------------------------------------------------------------
def test_from_checkpoint_equals_the_constructor(tiny_model, tmp_path):
    from beadsight.checkpoint import load_checkpoint

    path = tiny_model.save(tmp_path / "tiny.pt")
    settings = PredictorSettings(on_gap="hold", max_gap_frames=1)
    loaded = PressurePredictor.from_checkpoint(path, "torch", "fp32", settings=settings)
    model = load_checkpoint(path)
    built = PressurePredictor(model, TorchBackend(model), settings=settings)
    assert loaded.settings == built.settings == settings
    frames = _frames(T + 8)
    times = np.arange(T + 8) / FPS
    times[T + 2 :] += 4 / FPS  # a gap the hold policy fills
    for frame, t in zip(frames, times, strict=True):
        a, b = loaded.update(frame, t), built.update(frame, t)
        assert (a is None) == (b is None)
        if a is not None:
            for field in dataclasses.fields(PressureReading):
                if field.name != "latency_s":
                    np.testing.assert_array_equal(getattr(a, field.name), getattr(b, field.name))
    assert loaded.dropped_frames == built.dropped_frames == 4


def test_constructor_does_no_file_work(tiny_model, monkeypatch):
    """PressurePredictor(model) neither loads nor probes: only from_checkpoint does."""
    import beadsight.inference.predictor as predictor_module

    def refuse(*args, **kwargs):
        raise AssertionError("the constructor loaded or probed")

    monkeypatch.setattr(predictor_module, "load_checkpoint", refuse)
    monkeypatch.setattr(predictor_module, "create_backend", refuse)
    predictor = PressurePredictor(tiny_model)
    assert predictor.backend.describe() == "torch/fp32"
    frames = _frames(T)
    for k in range(T):
        reading = predictor.update(frames[k], k / FPS)
    np.testing.assert_allclose(reading.pressure_kpa, tiny_model.predict(frames), atol=1e-5)
    with pytest.raises(AssertionError, match="loaded or probed"):
        PressurePredictor.from_checkpoint(tiny_model)


def test_constructor_takes_a_loaded_model_and_a_built_backend(tiny_model, tmp_path):
    path = tiny_model.save(tmp_path / "tiny.pt")
    with pytest.raises(TypeError, match=r"got PosixPath; .*PressurePredictor\.from_checkpoint"):
        PressurePredictor(path)
    with pytest.raises(TypeError, match=r"backend must be a built Backend or None, got str"):
        PressurePredictor(tiny_model, "torch")
    with pytest.raises(TypeError):  # settings is keyword-only; no other arguments
        PressurePredictor(tiny_model, None, PredictorSettings())
    with pytest.raises(TypeError):
        PressurePredictor(tiny_model, on_gap="hold")
