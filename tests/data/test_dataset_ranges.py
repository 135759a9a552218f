"""Issue 26: a dataset whose fps, forces or positions no rig produces is a named error when
opened, so info, train, evaluate, calibrate and export-dataset say so (never exit 70)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from beadsight.cli import main
from beadsight.data.dataset import DatasetError, open_dataset
from beadsight.data.reference_file import export_reference


def _edit(path, name, index, value):
    with h5py.File(path, "r+") as f:
        if name == "fps":
            f.attrs["fps"] = value
            return
        data = f[name][()]
        data[index] = value
        f[name][...] = data


@pytest.mark.parametrize(
    ("name", "index", "value", "message"),
    [
        ("fps", None, 0.0, "attribute 'fps' is 0; expected frames per second > 0 and <= 10000"),
        ("fps", None, -30.0, "attribute 'fps' is -30; expected frames per second > 0"),
        ("force", 7, 1e300, "field 'force' has 1 valid frame(s) outside -5 .. 100000 N"),
        ("force", 7, -50.0, "field 'force' has 1 valid frame(s) outside -5 .. 100000 N"),
        ("position", 7, 1e308, "field 'position' has 1 valid frame(s) outside -1000 .. 1000 mm"),
    ],
)
def test_out_of_range_dataset_is_a_named_error(make_dataset, name, index, value, message):
    data = make_dataset(presses=2, frames_per_press=20)
    _edit(data, name, index, value)
    with pytest.raises(
        DatasetError, match=rf"{data}: " + message.replace("(", r"\(").replace(")", r"\)")
    ):
        open_dataset(data)


@pytest.mark.parametrize("command", ["info", "train", "evaluate", "calibrate"])
def test_fps_zero_is_a_user_error_in_every_command(command, make_dataset, tiny_model, capsys):
    data = make_dataset(presses=4, frames_per_press=30)
    _edit(data, "fps", None, 0.0)
    checkpoint = tiny_model.save(data.parent / "m.pt")
    out = data.parent / "out"
    argv = {
        "info": ["info", str(data)],
        "train": ["train", "--data", str(data), "--out", str(out), "--steps", "1"],
        "evaluate": [
            "evaluate",
            "--checkpoint",
            str(checkpoint),
            "--data",
            str(data),
            "--out",
            str(out),
        ],
        "calibrate": [
            "calibrate",
            "--base",
            str(checkpoint),
            "--data",
            str(data),
            "--out",
            str(out),
        ],
    }[command]
    assert main([*argv, *([] if command == "info" else ["--no-progress"])]) == 1
    err = capsys.readouterr().err
    assert "attribute 'fps' is 0; expected frames per second > 0" in err
    assert "internal error" not in err


def test_export_dataset_refuses_values_float32_cannot_hold(make_dataset, tmp_path):
    data = make_dataset(presses=2, frames_per_press=20)
    with h5py.File(data, "r+") as f:  # an invalid frame: the dataset reads, float32 cannot hold it
        valid, force = f["valid"][()], f["force"][()]
        valid[0], force[0] = False, 1e300
        f["valid"][...], f["force"][...] = valid, force
    with pytest.raises(
        DatasetError, match=r"frame 0: forces .* does not fit the reference layout's float32"
    ):
        export_reference(data, tmp_path / "r.h5")
    assert not list(tmp_path.glob("r.h5*"))
    assert np.isfinite(open_dataset(data).force_n[1:]).all()
