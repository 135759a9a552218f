"""Export to ONNX / OpenVINO: parity at export, metadata, standalone use, refusals, CLI."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import onnx
import pytest
import torch

import beadsight.inference.export as export_module
from beadsight import PressurePredictor
from beadsight.checkpoint import PressureModel
from beadsight.cli import main
from beadsight.inference.backend import BackendUnavailableError
from beadsight.inference.export import export_model
from beadsight.inference.export_format import (
    FINGERPRINT_KEY,
    META_KEY,
    ExportError,
    model_fingerprint,
    read_exported_metadata,
)
from beadsight.inference.parity import probe_window


@pytest.fixture
def checkpoint(tiny_model, tmp_path):
    return tiny_model.save(tmp_path / "tiny.pt")


def test_onnx_export_parity_and_metadata(tiny_model, tmp_path):
    report = export_model(tiny_model, "onnx", tmp_path / "m.onnx")
    assert report.max_abs_err_kpa <= 1e-4
    assert report.peak_kpa > 0 and report.path.endswith("m.onnx")
    meta = read_exported_metadata(report.path)
    assert json.loads(meta[META_KEY]) == json.loads(tiny_model.meta.to_json())
    assert meta[FINGERPRINT_KEY] == model_fingerprint(tiny_model) == report.fingerprint
    proto = onnx.load(report.path)
    (inp,) = proto.graph.input
    assert inp.name == "frames"
    assert inp.type.tensor_type.elem_type == onnx.TensorProto.UINT8


@pytest.mark.parametrize("frame_stride", [1, 3])
def test_exported_onnx_runs_without_beadsight(tiny_model, tmp_path, frame_stride):
    """The docstring's snippet, run by a plain interpreter that never imports beadsight."""
    model = tiny_model
    if frame_stride > 1:
        config = dataclasses.replace(tiny_model.meta.model, frame_stride=frame_stride)
        model = PressureModel.create(dataclasses.replace(tiny_model.meta, model=config))
        model.module.load_state_dict(tiny_model.module.state_dict())
    path = export_model(model, "onnx", tmp_path / "beadsight.onnx").path
    window = probe_window(model)[0]
    np.save(tmp_path / "window.npy", window)
    np.save(tmp_path / "expected.npy", model.predict(window))
    snippet = re.search(r"without beadsight.*?::\n\n(.*?)\n\n", export_module.__doc__, re.S)
    code = textwrap.dedent(snippet.group(1)).replace('"beadsight.onnx"', repr(str(path)))
    code = code.replace(
        "frames = np.zeros((1, t, s, s, 3), np.uint8)",
        f"frames = np.load({str(tmp_path / 'window.npy')!r})[None]",
    )
    code += textwrap.dedent(f"""
        import sys
        assert "beadsight" not in sys.modules, "beadsight was imported"
        expected = np.load({str(tmp_path / "expected.npy")!r})
        assert frames.shape[1] == t == {model.span}, (frames.shape, t)
        assert pressure_kpa.shape == expected.shape == (s, s), pressure_kpa.shape
        print(float(np.abs(pressure_kpa - expected).max()))
    """)
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr
    assert float(done.stdout.strip()) <= 1e-4


def test_exported_onnx_has_a_dynamic_batch(tiny_model, tmp_path):
    import onnxruntime as ort

    path = export_model(tiny_model, "onnx", tmp_path / "m.onnx").path
    rng = np.random.default_rng(3)
    batch = rng.integers(0, 256, (3, 15, 64, 64, 3), dtype=np.uint8)
    out = ort.InferenceSession(path).run(None, {"frames": batch})[0]
    np.testing.assert_allclose(out, tiny_model.predict(batch), atol=1e-4, rtol=0)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_openvino_export_parity_and_metadata(tiny_model, tmp_path, precision):
    from beadsight.inference.runtimes import openvino_supports_bf16

    if precision == "bf16" and not openvino_supports_bf16():  # refused, never run emulated
        with pytest.raises(BackendUnavailableError, match="this CPU has no native bf16"):
            export_model(tiny_model, "openvino", tmp_path / "ov" / "m.xml", precision)
        return
    report = export_model(tiny_model, "openvino", tmp_path / "ov" / "m.xml", precision)
    assert report.path.endswith("m.xml") and (tmp_path / "ov" / "m.bin").is_file()
    if precision == "fp32":
        assert report.max_abs_err_kpa <= 1e-4
    else:
        assert report.max_abs_err_kpa <= 0.01 * max(report.peak_kpa, 4.0)
    meta = read_exported_metadata(report.path)
    assert meta[FINGERPRINT_KEY] == model_fingerprint(tiny_model)
    assert meta["beadsight_precision"] == precision
    predictor = PressurePredictor.from_checkpoint(tiny_model, exported_model=report.path)
    assert predictor.backend.describe() == f"openvino/{precision}"


def test_mismatched_exported_model_is_refused(tiny_model, tmp_path):
    path = export_model(tiny_model, "onnx", tmp_path / "m.onnx").path
    torch.manual_seed(99)
    other = PressureModel.create(tiny_model.meta)  # same description, other weights
    with pytest.raises(ExportError, match=r"m\.onnx was exported from a different checkpoint"):
        PressurePredictor.from_checkpoint(other, backend="onnx", exported_model=path)


def test_file_without_metadata_is_refused(tiny_model, tmp_path):
    path = export_model(tiny_model, "onnx", tmp_path / "m.onnx").path
    proto = onnx.load(path)
    del proto.metadata_props[:]
    onnx.save(proto, path)
    with pytest.raises(ExportError, match=r"m\.onnx: no beadsight metadata"):
        PressurePredictor.from_checkpoint(tiny_model, exported_model=path)


def test_bad_export_requests(tiny_model, tmp_path):
    with pytest.raises(ExportError, match="fp32 only"):
        export_model(tiny_model, "onnx", tmp_path / "m.onnx", precision="bf16")
    with pytest.raises(ValueError, match="format must be one of"):
        export_model(tiny_model, "tflite", tmp_path / "m.tflite")
    with pytest.raises(FileNotFoundError, match="missing.onnx"):
        read_exported_metadata(tmp_path / "missing.onnx")
    assert not list(tmp_path.iterdir())  # nothing half-written was left behind


def test_cli_export(checkpoint, tmp_path, capsys):
    out = tmp_path / "cli.onnx"
    assert (
        main(
            [
                "export",
                "--checkpoint",
                str(checkpoint),
                "--format",
                "onnx",
                "--out",
                str(out),
                "--json",
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["path"] == str(out) and report["max_abs_err_kpa"] <= 1e-4
    assert (
        main(
            [
                "export",
                "--checkpoint",
                str(tmp_path / "nope.pt"),
                "--format",
                "onnx",
                "--out",
                str(out),
            ]
        )
        == 1
    )
    assert "nope.pt" in capsys.readouterr().err


def test_openvino_export_sends_no_telemetry_and_writes_nothing_home(checkpoint, tmp_path):
    """``import openvino`` (and its converter, ``convert_model``) report usage to Google
    Analytics and write ``~/intel`` unless a consent file or CI=true says no.
    ``beadsight export``, run as a user runs it (a fresh process, no CI variable), must do
    neither."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TF_BUILD", "JENKINS_URL")}
    code = (
        "import sys\n"
        "from beadsight.cli import main\n"
        f"code = main(['export', '--checkpoint', {str(checkpoint)!r}, '--format', 'openvino',"
        f" '--out', {str(tmp_path / 'ov' / 'm.xml')!r}])\n"
        "assert sys.modules.get('openvino_telemetry') is None, 'telemetry loaded'\n"
        "sys.exit(code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**env, "HOME": str(home)},
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "ov" / "m.bin").is_file()
    assert not list(home.iterdir())  # no ~/intel/openvino_ga_cid, no stats


def test_cli_bench_live_json(checkpoint, tmp_path, capsys):
    code = main(
        [
            "bench",
            "live",
            "--checkpoint",
            str(checkpoint),
            "--json",
            "--frames",
            "60",
            "--cache-dir",
            str(tmp_path / "cache"),
            "--precision",  # auto among the fp32 runtimes: int8's quantisation and bf16 are
            "fp32",  # timed by test_int8 and test_select
        ]
    )
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    for key in ("hz", "p50_ms", "p99_ms", "max_ms", "max_abs_err_pct", "backend"):
        assert key in result, key
    assert result["hz"] > 0 and 0 < result["p50_ms"] <= result["p99_ms"] <= result["max_ms"]
    assert result["max_abs_err_pct"] <= 1.0
    assert result["throughput"]["readings"] == 60 - 15 + 1
    sustained = result["sustained"]
    assert sustained["offered_hz"] == 30.0 and sustained["readings"] >= 1


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--reference", "r.pt"], "--reference goes with --tiers"),
        (["--tiers", "--rate", "0"], "--rate must be > 0 Hz, got 0"),
    ],
)
def test_cli_bench_live_refuses_options_it_would_ignore(extra, message, capsys):
    assert main(["bench", "live", *extra]) == 1  # a user error
    assert message in capsys.readouterr().err
