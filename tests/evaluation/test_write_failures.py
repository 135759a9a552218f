"""predict and evaluate on a real full disk (a 256 KiB tmpfs): a named error, a non-zero exit,
and never a damaged file under its final name (issue 13, item 14)."""

from __future__ import annotations

import h5py
import pytest
from PIL import Image

from beadsight.cli import main
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.evaluation.predict import predict_recording
from beadsight.files import WriteError


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith((".partial", ".tmp")))


def test_predict_on_a_full_disk_exits_non_zero_and_leaves_no_file(
    make_dataset, tiny_model, tmp_path, full_disk, capsys
):
    data = make_dataset(presses=6, frames_per_press=40)  # 240 maps of 64x64 float32: ~4 MB
    checkpoint = tiny_model.save(tmp_path / "tiny.pt")
    out = full_disk / "pressure.h5"
    argv = [
        "predict",
        "--checkpoint",
        str(checkpoint),
        "--input",
        str(data),
        "--out",
        str(out),
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert f"could not write {out}" in err and "disk full" in err
    assert "Traceback" not in err
    assert not out.exists()
    assert _leftovers(full_disk) == []  # the partial file was removed, freeing the disk


def test_predict_write_error_keeps_an_earlier_result(make_dataset, tiny_model, full_disk):
    data = make_dataset(presses=6, frames_per_press=40)
    out = full_disk / "pressure.h5"
    out.write_bytes(b"an earlier result")
    with pytest.raises(WriteError, match=r"pressure\.h5.*disk full"):
        predict_recording(tiny_model, data, out, device="cpu", progress=False, overwrite=True)
    assert out.read_bytes() == b"an earlier result"
    assert _leftovers(full_disk) == []


def test_evaluate_on_a_full_disk_exits_non_zero(
    make_dataset, tiny_model, tmp_path, full_disk, capsys
):
    data = make_dataset(presses=6, frames_per_press=40)
    checkpoint = tiny_model.save(tmp_path / "tiny.pt")
    out = full_disk / "eval"
    argv = [
        "evaluate",
        "--checkpoint",
        str(checkpoint),
        "--data",
        str(data),
        "--split",
        "all",
        "--out",
        str(out),
        "--device",
        "cpu",
        "--batch-size",
        "2",
        "--baselines",
        "--no-progress",
    ]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "could not write" in err and "predictions.h5" in err and "disk full" in err
    assert not (out / "predictions.h5").exists() and not (out / "metrics.json").exists()
    assert _leftovers(out) == []


def test_evaluate_full_disk_after_the_predictions(make_dataset, tiny_model, full_disk):
    """Predictions fit, a later file does not: whatever has its final name is complete."""
    data = make_dataset(presses=6, frames_per_press=40)
    out = full_disk / "eval"
    with pytest.raises(WriteError, match="disk full"):
        evaluate(
            tiny_model,
            data,
            EvaluateConfig(split="all", device="cpu", max_frames=3, baselines=True, progress=False),
            out,
        )
    assert (out / "predictions.h5").is_file()  # 3 frames fit
    with h5py.File(out / "predictions.h5", "r") as f:
        assert f["pred_kpa"].shape == (3, 64, 64)
    for png in out.glob("*.png"):
        Image.open(png).load()  # every image under its final name decodes in full
    assert not (out / "index.html").exists() and not (out / "metrics.json").exists()
    assert _leftovers(out) == []
