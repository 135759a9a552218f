"""``frames`` (T, what the network sees) and ``span`` (what a window covers) everywhere; files
and names of beadsight 0.1 keep working, the names with a DeprecationWarning."""

from __future__ import annotations

import dataclasses
import importlib
import json
import sys
import warnings

import numpy as np
import pytest
import torch
from inference_helpers import stream

import beadsight
from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.config import ConfigError, ModelConfig
from beadsight.inference.predictor import PressurePredictor, PressureReading
from beadsight.inference.runtimes import TorchBackend


@pytest.fixture
def no_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


def _v01_checkpoint(model: PressureModel, path):
    """``model`` saved the way beadsight 0.1 did: metadata format 1, ``window`` for T."""
    meta = json.loads(model.meta.to_json())
    meta["format_version"] = 1
    meta["model"]["window"] = meta["model"].pop("frames")
    state = {k: v.clone() for k, v in model.module.net.state_dict().items()}
    torch.save({"beadsight": json.dumps(meta), "state_dict": state, "step": 3}, path)
    return path


# --- frames and span ----------------------------------------------------------------
def test_frames_and_span_of_a_strided_model(strided_model, no_warnings):
    assert strided_model.meta.model.frames == strided_model.frames == 15
    assert strided_model.meta.model.span == strided_model.span == 43  # (15 - 1) * 3 + 1
    module = strided_model.module
    assert (module.frames, module.span) == (15, 43)
    assert module.net.C1.layer[0].in_channels == 3 * 15  # the network sees T frames
    backend = TorchBackend(strided_model)
    assert (backend.frames, backend.span) == (15, 43)
    predictor = PressurePredictor(strided_model, backend)
    assert (predictor.frames, predictor.span) == (15, 43)
    frames = stream(43)
    readings = [predictor.update(f, k / 30) for k, f in enumerate(frames)]
    assert [r is None for r in readings] == [True] * 42 + [False]  # a window is 43 frames
    np.testing.assert_allclose(
        readings[-1].pressure_kpa, strided_model.predict(frames), atol=1e-5, rtol=0
    )


def test_deprecated_window_keeps_its_old_meaning(strided_model):
    """ModelConfig.window was T; the other objects' .window was the span."""
    config = strided_model.meta.model
    with pytest.deprecated_call(match=r"ModelConfig\.window is deprecated.*ModelConfig\.frames"):
        assert config.window == 15
    predictor = PressurePredictor(strided_model)
    for obj in (strided_model, strided_model.module, predictor.backend, predictor):
        with pytest.deprecated_call(match=r"\.window is deprecated.*use .*\.span"):
            assert obj.window == 43


def test_old_config_keys_are_mapped_with_a_warning():
    with pytest.deprecated_call(match="'window' is now 'frames'"):
        assert ModelConfig(window=4, frame_stride=2) == ModelConfig(frames=4, frame_stride=2)
    with pytest.deprecated_call():
        assert ModelConfig.from_dict({"window": 5}).frames == 5
    with pytest.raises(ConfigError, match="'window' and 'frames' both given"):
        ModelConfig.from_dict({"window": 5, "frames": 5})


def test_old_toml_key_is_mapped_naming_the_file(make_dataset, tmp_path):
    from beadsight.train.config import TrainConfig, resolve_train_config

    toml = tmp_path / "run.toml"
    toml.write_text(f'data = "{make_dataset()}"\nout = "{tmp_path / "run"}"\nwindow = 7\n')
    with pytest.warns(FutureWarning, match=r"run\.toml: TrainConfig: 'window' is now 'frames'"):
        config = resolve_train_config({}, toml)
    assert config.frames == 7 and config.model_config().frames == 7
    with pytest.deprecated_call():
        assert TrainConfig(data="d.h5", out="o", window=3).frames == 3


# --- files of beadsight 0.1 ---------------------------------------------------------
def test_v01_checkpoint_loads_silently(strided_model, tmp_path, no_warnings):
    path = _v01_checkpoint(strided_model, tmp_path / "v01.pt")
    model = load_checkpoint(path)
    assert model.meta.model == strided_model.meta.model
    assert (model.frames, model.span) == (15, 43)
    frames = stream(43)
    np.testing.assert_array_equal(model.predict(frames), strided_model.predict(frames))
    resaved = load_checkpoint(model.save(tmp_path / "v02.pt"))  # written in format 2
    stored = json.loads(torch.load(tmp_path / "v02.pt", weights_only=True)["beadsight"])
    assert stored["format_version"] == 2 and stored["model"]["frames"] == 15
    assert "window" not in stored["model"] and resaved.meta.model == model.meta.model


def test_onnx_file_exported_by_v01_still_matches_its_checkpoint(probe_model, tmp_path):
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from beadsight.inference import exported

    path = exported.write_onnx(probe_model, tmp_path / "v01.onnx")
    proto = onnx.load(str(path))
    old = load_checkpoint(_v01_checkpoint(probe_model, tmp_path / "v01.pt"))
    meta = json.loads(old.meta.to_json())
    meta["format_version"], meta["model"]["window"] = 1, meta["model"].pop("frames")
    old_json = json.dumps(meta, sort_keys=True)
    fingerprint = exported._fingerprint(old_json, old)  # what 0.1 computed
    for entry in proto.metadata_props:
        if entry.key == exported.META_KEY:
            entry.value = old_json
        elif entry.key == exported.FINGERPRINT_KEY:
            entry.value = fingerprint
    onnx.save(proto, str(path))
    predictor = PressurePredictor.from_checkpoint(old, exported_model=path)
    assert predictor.backend.describe() == "onnx/fp32"
    torch.manual_seed(5)
    other = PressureModel.create(probe_model.meta)
    with pytest.raises(exported.ExportError, match="different checkpoint"):
        PressurePredictor.from_checkpoint(other, exported_model=path)


# --- deprecated names ---------------------------------------------------------------
def test_reading_aliases_warn_and_are_the_new_class():
    with pytest.deprecated_call(match=r"beadsight\.Reading is deprecated.*PressureReading"):
        assert beadsight.Reading is PressureReading
    from beadsight.inference import predictor

    with pytest.deprecated_call(match="Reading is deprecated"):
        assert predictor.Reading is PressureReading
    from beadsight import devices
    from beadsight.devices import base

    with pytest.deprecated_call(match=r"devices\.Reading is deprecated.*ScaleReading"):
        assert devices.Reading is devices.ScaleReading
    with pytest.deprecated_call(match=r"base\.Reading is deprecated.*ScaleReading"):
        assert base.Reading is devices.ScaleReading
    with pytest.deprecated_call(match="otsu_threshold is deprecated"):
        threshold = predictor.otsu_threshold
    assert 5.0 < threshold(np.array([5.0] * 10 + [50.0] * 10)) <= 50.0


def test_old_module_paths_keep_their_names():
    for name in ("beadsight.backends", "beadsight.export", "beadsight.predictor"):
        sys.modules.pop(name, None)
    with pytest.deprecated_call(match="beadsight.backends is deprecated"):
        backends = importlib.import_module("beadsight.backends")
    for name in ("create_backend", "select_backend", "check_parity", "probe_window",
                 "TorchBackend", "ParityError", "default_cache_dir", "CHOICE_FILE"):  # fmt: skip
        assert hasattr(backends, name), name
    with pytest.deprecated_call():
        export = importlib.import_module("beadsight.export")
    for name in ("export_model", "model_fingerprint", "read_exported_metadata", "ExportError"):
        assert hasattr(export, name), name


def test_predictor_built_the_v01_way_warns_and_works(probe_model, tmp_path):
    path = probe_model.save(tmp_path / "m.pt")
    with pytest.deprecated_call(match="from_checkpoint"):
        old = PressurePredictor(path, "torch", "fp32", on_gap="hold")
    new = PressurePredictor.from_checkpoint(path, "torch", "fp32", on_gap="hold")
    assert old.on_gap == new.on_gap == "hold" and old.backend.describe() == "torch/fp32"
    with pytest.deprecated_call():
        PressurePredictor(probe_model, backend="torch", precision="fp32")


def test_live_sensor_v01_keywords_warn_and_map(probe_model):
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    with pytest.deprecated_call(match="LiveSettings"):
        sensor = LiveSensor(probe_model, "sim", "torch", "fp32", fps=15, preprocess=None,
                            reconnect_backoff_s=(0.1, 0.2), max_readings=3,
                            predictor_options={"on_gap": "hold"})  # fmt: skip
    assert sensor.settings == LiveSettings(
        backend="torch", precision="fp32", source_fps=15, preprocess="auto",
        reconnect_initial_s=0.1, reconnect_max_s=0.2, max_readings=3,
        predictor=dataclasses.replace(LiveSettings().predictor, on_gap="hold"),
    )  # fmt: skip
    with pytest.deprecated_call(match="beadsight.live.run_live is deprecated"):
        from beadsight.live import run_live
    from beadsight.live.run import run_live as new

    assert run_live is new


def test_live_settings_are_checked_when_made():
    from beadsight.live.settings import LiveSettings

    for field, value, message in [
        ("backend", "tensorrt", "backend must be"),
        ("precision", "fp16", "precision must be"),
        ("preprocess", "fisheye", "preprocess 'fisheye'"),
        ("no_signal_after_s", 0, "no_signal_after_s must be a number > 0"),
        ("reconnect_max_s", 0.1, "reconnect_max_s .* must not be below"),
        ("max_readings", 0, "max_readings must be an integer >= 1"),
        ("source_fps", float("inf"), "source_fps must be finite"),
    ]:
        with pytest.raises(ConfigError, match=message):
            LiveSettings(**{field: value})
