"""evaluate and predict run through live's runtimes (--backend): same metrics on torch,
ONNX Runtime and OpenVINO; unknown names are refused by name."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from beadsight.cli import main
from beadsight.evaluation.config import EvaluateConfig, EvaluationError
from beadsight.evaluation.evaluate import evaluate
from beadsight.evaluation.predict import predict_recording
from beadsight.inference.backend import BackendUnavailableError

KEYS = ("mae_kpa", "force_error_pct", "cop_error_mm", "iou", "worst_region_mae_kpa")


@pytest.fixture
def data(make_dataset):
    return make_dataset(presses=3, frames_per_press=30)


def test_evaluate_scores_the_same_on_torch_onnx_and_openvino(tiny_model, data, tmp_path):
    scored = {}
    for backend in ("torch", "onnx", "openvino"):
        config = EvaluateConfig(
            split="all", backend=backend, device="cpu", plots=False, report=False, progress=False
        )  # the scores and predictions are compared; plots and report have their own tests
        scored[backend] = evaluate(tiny_model, data, config, tmp_path / backend)
        assert scored[backend]["backend"] == f"{backend}/fp32"
        assert scored[backend]["config"]["backend"] == backend
    for backend in ("onnx", "openvino"):
        assert scored[backend]["frames"] == scored["torch"]["frames"] > 0
        for key in KEYS:
            assert scored[backend][key] == pytest.approx(scored["torch"][key], rel=1e-4, abs=1e-5)
    with h5py.File(tmp_path / "torch" / "predictions.h5") as a:
        with h5py.File(tmp_path / "onnx" / "predictions.h5") as b:
            assert np.abs(a["pred_kpa"][()] - b["pred_kpa"][()]).max() < 1e-3


def test_bad_backend_or_precision_is_a_named_error(tiny_model, data, tmp_path, capsys):
    with pytest.raises(EvaluationError, match=r"--backend must be one of .*'tensorrt'"):
        EvaluateConfig(backend="tensorrt")
    with pytest.raises(EvaluationError, match=r"--precision must be one of .*'fp8'"):
        EvaluateConfig(precision="fp8")
    with pytest.raises(EvaluationError, match="--backend"):
        predict_recording(tiny_model, data, tmp_path / "p.h5", backend="tensorrt")
    with pytest.raises(BackendUnavailableError, match="onnx.*bf16"):  # a precision it lacks
        evaluate(tiny_model, data, EvaluateConfig(backend="onnx", precision="bf16"))
    argv = ["evaluate", "--checkpoint", "x.pt", "--data", str(data), "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--backend", "tensorrt"])
    assert exit_.value.code == 2
    assert "--backend: invalid choice: 'tensorrt'" in capsys.readouterr().err


def test_predict_through_onnx_matches_torch(tiny_model, data, tmp_path):
    maps = {}
    for backend in ("torch", "onnx"):
        out = predict_recording(
            tiny_model, data, tmp_path / f"{backend}.h5", backend=backend, progress=False
        )
        with h5py.File(out) as f:
            assert f.attrs["backend"] == f"{backend}/fp32"
            maps[backend] = f["pressure_kpa"][()]
            assert f["valid"][()].sum() > 0
    assert np.abs(maps["torch"] - maps["onnx"]).max() < 1e-3
