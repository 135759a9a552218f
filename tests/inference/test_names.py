"""``frames`` (T, what the network sees) and ``span`` (what a window covers) everywhere;
``window`` is no attribute, setting or checkpoint key."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from helpers.inference import stream

from beadsight.checkpoint import CheckpointError, load_checkpoint
from beadsight.config import ConfigError, ModelConfig
from beadsight.inference.predictor import PressurePredictor
from beadsight.inference.runtimes import TorchBackend


@pytest.fixture
def no_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


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


def test_window_is_no_name_for_a_frame_count(strided_model, make_dataset, tmp_path):
    predictor = PressurePredictor(strided_model)
    objects = [strided_model.meta.model, strided_model, strided_model.module]
    for obj in [*objects, predictor.backend, predictor]:
        assert not hasattr(obj, "window"), type(obj).__name__
    with pytest.raises(TypeError, match="window"):
        ModelConfig(window=4)
    from beadsight.train.config import resolve_train_config

    toml = tmp_path / "run.toml"
    toml.write_text(f'data = "{make_dataset()}"\nout = "{tmp_path / "run"}"\nwindow = 7\n')
    with pytest.raises(ConfigError, match=r"unknown training setting\(s\) \['window'\]"):
        resolve_train_config({}, toml)


def test_checkpoint_of_another_format_version_is_refused(probe_model, tmp_path):
    """Format 1 (never released) named T ``window``; read as format 2 it would silently
    build a model of the default frame count, so it is refused."""
    meta = json.loads(probe_model.meta.to_json())
    meta["format_version"] = 1
    meta["model"]["window"] = meta["model"].pop("frames")
    state = {k: v.clone() for k, v in probe_model.module.net.state_dict().items()}
    for version, path, match in [
        (1, tmp_path / "v1.pt", r"format_version 1; this beadsight reads versions \(2, 3, 4\)$"),
        (5, tmp_path / "v5.pt", r"format_version 5; .*versions \(2, 3, 4\); upgrade beadsight"),
        (None, tmp_path / "none.pt", r"format_version None; "),
    ]:
        meta["format_version"] = version
        torch.save({"beadsight": json.dumps(meta), "state_dict": state}, path)
        with pytest.raises(CheckpointError, match=match):
            load_checkpoint(path)


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
