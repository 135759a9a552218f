"""The parity check: probe windows with pressure in them, and a runtime that disagrees with
fp32 torch refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.inference import T

from beadsight.checkpoint import PressureModel
from beadsight.inference.parity import PARITY_TOLERANCE, ParityError, probe_window
from beadsight.inference.predictor import PressurePredictor


def test_probe_window_has_a_real_peak(probe_model):
    window = probe_window(probe_model)
    assert window.shape == (1, T, 64, 64, 3) and window.dtype == np.uint8
    assert probe_model.predict(window[0]).max() > PARITY_TOLERANCE.floor_kpa
    np.testing.assert_array_equal(window, probe_window(probe_model))  # deterministic


def test_named_backend_that_disagrees_is_refused(probe_model, tmp_path):
    """An ONNX file whose metadata claims this checkpoint but holds other weights."""
    import onnx

    from beadsight.inference.export_format import exported_metadata, write_onnx

    torch.manual_seed(123)
    impostor = PressureModel.create(probe_model.meta)
    path = write_onnx(impostor, tmp_path / "impostor.onnx")
    proto = onnx.load(str(path))
    for entry in proto.metadata_props:  # forge the metadata
        entry.value = exported_metadata(probe_model)[entry.key]
    onnx.save(proto, str(path))
    with pytest.raises(ParityError, match="disagrees with fp32 torch"):
        PressurePredictor.from_checkpoint(probe_model, "onnx", exported_model=path)
