"""Issue 26: flags a new user meets -- help text for every --format, export's default model
like live and health, and no switch that does nothing (calibrate --no-gain)."""

from __future__ import annotations

import pytest

from beadsight.assets import shipped_model_path
from beadsight.checkpoint import load_checkpoint
from beadsight.cli import build_parser, main
from beadsight.inference.export_format import model_fingerprint, read_exported_metadata


def _help(command: str, capsys) -> str:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    return " ".join(capsys.readouterr().out.split())


def test_format_flags_have_help(capsys):
    assert "onnx: an .onnx file for onnxruntime; openvino: an OpenVINO IR" in _help(
        "export", capsys
    )
    text = _help("export-dataset", capsys)
    assert "reference: the original BeadSight code's processed HDF5 layout" in text


def test_calibrate_has_no_switch_that_does_nothing(capsys):
    with pytest.raises(SystemExit) as exit:
        main(["calibrate", "--data", "d.h5", "--out", "o", "--no-gain"])
    assert exit.value.code == 2
    assert "unrecognized arguments: --no-gain" in capsys.readouterr().err
    parser = build_parser(["calibrate"])
    args = parser.parse_args(["calibrate", "--data", "d.h5", "--out", "o", "--gain"])
    assert args.gain is True


def test_export_defaults_to_the_shipped_model_like_live_and_health(tmp_path, capsys):
    out = tmp_path / "model.onnx"
    assert main(["export", "--format", "onnx", "--out", str(out)]) == 0
    assert f"wrote {out} (onnx, fp32)" in capsys.readouterr().out
    shipped = model_fingerprint(load_checkpoint(shipped_model_path()))
    assert shipped in read_exported_metadata(out).values()
