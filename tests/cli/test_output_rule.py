"""Issue 26, item 2: one rule for every command that writes. An existing output file is
refused without --overwrite; an output folder that holds anything is refused without
--overwrite; a file where a folder is expected is a named error (never exit 70)."""

from __future__ import annotations

import pytest

from beadsight.cli import main
from beadsight.files import OutputExistsError, prepare_output_folder


@pytest.fixture
def checkpoint(tiny_model, tmp_path):
    return tiny_model.save(tmp_path / "model.pt")


def _refused(argv, capsys) -> str:
    assert main([str(a) for a in argv]) == 1
    return capsys.readouterr().err


def test_predict_refuses_an_existing_out_without_overwrite(checkpoint, make_dataset, capsys):
    data = make_dataset(presses=2, frames_per_press=20)
    out = data.parent / "other.h5"
    out.write_bytes(b"somebody else's dataset")
    argv = ["predict", "--checkpoint", checkpoint, "--input", data, "--out", out, "--no-progress"]
    err = _refused(argv, capsys)
    assert f"{out}: already exists; choose another output name, or pass --overwrite" in err
    assert out.read_bytes() == b"somebody else's dataset"
    assert main([str(a) for a in argv] + ["--overwrite"]) == 0
    assert out.read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"


def test_export_refuses_an_existing_out_without_overwrite(checkpoint, tmp_path, capsys):
    out = tmp_path / "model.onnx"
    out.write_text("not ours")
    err = _refused(["export", "--checkpoint", checkpoint, "--format", "onnx", "--out", out], capsys)
    assert f"{out}: already exists; choose another output name, or pass --overwrite" in err
    assert out.read_text() == "not ours"


def test_evaluate_refuses_a_folder_that_holds_other_files(checkpoint, make_dataset, capsys):
    data = make_dataset(presses=4, frames_per_press=30)
    out = data.parent / "results"
    out.mkdir()
    (out / "metrics.json").write_text("my own notes")
    argv = ["evaluate", "--checkpoint", checkpoint, "--data", data, "--out", out, "--no-plots"]
    err = _refused([*argv, "--no-progress"], capsys)
    assert f"{out}: folder exists and is not empty; choose another output folder" in err
    assert (out / "metrics.json").read_text() == "my own notes"
    assert main([str(a) for a in argv] + ["--no-progress", "--overwrite"]) == 0
    assert (out / "metrics.json").read_text() != "my own notes"


@pytest.mark.parametrize("command", ["evaluate", "calibrate", "train"])
def test_out_naming_a_file_where_a_folder_is_expected_is_a_named_error(
    command, checkpoint, make_dataset, capsys
):
    data = make_dataset(presses=4, frames_per_press=30)
    out = data.parent / "a_file"
    out.write_text("x")
    argv = {
        "evaluate": ["--checkpoint", checkpoint, "--no-progress"],
        "calibrate": ["--base", checkpoint, "--budget-min", "0.05", "--no-progress"],
        "train": ["--steps", "1", "--no-progress"],
    }[command]
    err = _refused([command, "--data", data, "--out", out, *argv], capsys)
    assert f"{out}: is a file; expected a" in err
    assert "internal error" not in err
    assert out.read_text() == "x"


def test_calibrate_refuses_a_folder_without_its_own_files(checkpoint, make_dataset, capsys):
    data = make_dataset(presses=6, frames_per_press=40)
    out = data.parent / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    err = _refused(
        ["calibrate", "--data", data, "--out", out, "--base", checkpoint, "--no-progress"],
        capsys,
    )
    assert f"{out}: folder exists and is not empty" in err and "--overwrite" in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_prepare_output_folder_creates_and_accepts_an_empty_folder(tmp_path):
    assert prepare_output_folder(tmp_path / "a" / "b").is_dir()
    assert prepare_output_folder(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    (tmp_path / "a" / "b" / "f").write_text("")
    with pytest.raises(OutputExistsError, match="not empty"):
        prepare_output_folder(tmp_path / "a" / "b")
    assert prepare_output_folder(tmp_path / "a" / "b", overwrite=True).is_dir()
