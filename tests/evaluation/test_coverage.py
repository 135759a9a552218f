"""Issue 13 items 4 and 7: evaluation covers the recording; reference checkpoints keep
their own split.

The reference checkpoint here is a training dict shaped like the reference's
(model_training.py): train_indices / test_indices are window-end frame indices into the
HDF5 file at dataset_path (valid, in-contact frames of whole presses).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_checkpoint import reference_training_dict

from beadsight import load_checkpoint
from beadsight.cli import main
from beadsight.config import ModelConfig
from beadsight.data.dataset import open_dataset
from beadsight.data.reference_file import export_reference
from beadsight.data.rest import rest_ends
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import EvaluationError, evaluate
from beadsight.model import UNet
from beadsight.train.config import TrainConfig
from beadsight.train.trainer import train

SPAN = 15
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_short_presses_are_evaluated_on_every_frame_with_history(make_dataset, tiny_model):
    """Presses of 12 frames are shorter than the 15-frame window: windows reach into the
    previous press, so every valid frame after the first 14 is evaluated."""
    data = make_dataset(presses=10, frames_per_press=12)
    metrics = evaluate(tiny_model, data, EvaluateConfig(split="all", device="cpu", progress=False))
    with open_dataset(data) as ds:
        n = len(ds)
        assert ds.num_presses == 10 and ds.valid.all()
    assert metrics["frames"] == n - (SPAN - 1)
    assert metrics["valid_frames"] == n
    assert metrics["coverage"] == pytest.approx((n - SPAN + 1) / n)
    assert metrics["window_coverage"] == metrics["coverage"]  # no --max-frames sample
    sampled = evaluate(
        tiny_model, data, EvaluateConfig(split="all", device="cpu", progress=False, max_frames=20)
    )
    assert sampled["frames"] == 20 and sampled["coverage"] == pytest.approx(20 / n)
    assert sampled["window_coverage"] == metrics["window_coverage"]
    assert metrics["presses"] >= 9  # the first press's frames lack 14 frames of history


def test_coverage_in_metrics_json_and_printed(make_dataset, tiny_model, tmp_path, capsys):
    data = make_dataset(presses=6, frames_per_press=20)
    model = tiny_model.save(tmp_path / "m.pt")
    out = tmp_path / "eval"
    code = main(
        [
            "evaluate",
            "--checkpoint",
            str(model),
            "--data",
            str(data),
            "--split",
            "all",
            "--out",
            str(out),
            "--device",
            "cpu",
            "--no-plots",
            "--no-progress",
        ]
    )
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["coverage"] == pytest.approx((120 - 14) / 120)
    assert metrics["frames"] == 106 and metrics["valid_frames"] == 120
    assert "coverage: 88.3% of the split's 120 valid frames" in capsys.readouterr().out


def test_frames_without_a_rest_image_are_not_covered(rest_run, tmp_path, capsys):
    """A rest-referenced model scores frames with a full window and a rest image before
    them: the first press has none (8 unloaded frames, fewer than a settled run)."""
    data, checkpoint = rest_run
    out = tmp_path / "eval"
    argv = ["evaluate", "--checkpoint", checkpoint, "--data", data, "--split", "all", "--out", out]
    assert main([*map(str, argv), "--device", "cpu", "--no-plots", "--no-progress"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    with open_dataset(data) as ds:
        first_rest = int(np.argmax(rest_ends(ds.force_n, ds.valid) >= 0))
    assert first_rest == 46  # press 1's 8 unloaded frames after press 0's 8
    assert metrics["frames"] == 240 - first_rest and metrics["valid_frames"] == 240
    assert metrics["coverage"] == metrics["window_coverage"] == pytest.approx(194 / 240)
    printed = capsys.readouterr().out
    assert "coverage: 80.8% of the split's 240 valid frames" in printed
    assert "or a rest image before it" in printed


def test_a_test_split_window_may_reach_into_another_press(make_dataset, tiny_model):
    data = make_dataset(presses=6, frames_per_press=40)
    tiny_model.meta.training.update(split={"train": [0, 1, 2, 3], "val": [4], "test": [5]})
    metrics = evaluate(tiny_model, data, EvaluateConfig(split="test", device="cpu", progress=False))
    with open_dataset(data) as ds:
        press5 = np.flatnonzero(ds.press_id == 5)
    assert metrics["split_source"] == "checkpoint"
    assert metrics["frames"] == press5.size == metrics["valid_frames"]  # coverage 1.0
    assert metrics["coverage"] == 1.0


def test_training_on_presses_shorter_than_the_window(make_dataset, tmp_path):
    """Item 7, training: 10-frame presses and a 15-frame window (before: 'no training
    window fits')."""
    data = make_dataset(presses=8, frames_per_press=10)
    run = train(
        TrainConfig(
            data=str(data), out=str(tmp_path / "run"), width=8, steps=2, batch_size=4, device="cpu"
        )
    )
    split = json.loads((run / "split.json").read_text())
    assert split["windows"]["train"] > 0
    assert (run / "last.pt").is_file()


def test_dropped_frames_break_the_history(make_dataset, tiny_model, tmp_path):
    """A time gap (dropped frames) is not history: windows across it are not evaluated."""
    import h5py

    data = make_dataset(presses=4, frames_per_press=40)
    with h5py.File(data, "r+") as f:
        t = f["timestamp"][()]
        t[80:] += 1.0  # one second of frames lost before frame 80
        f["timestamp"][...] = t
    metrics = evaluate(tiny_model, data, EvaluateConfig(split="all", device="cpu", progress=False))
    assert metrics["frames"] == 160 - 2 * (SPAN - 1)


# --- item 4: reference checkpoints ------------------------------------------------------
@pytest.fixture
def reference_setup(make_dataset, tmp_path):
    """A reference-layout file and a reference checkpoint whose indices point into it."""
    ours = make_dataset(presses=6, frames_per_press=40, name="ours.h5")
    ref_file = export_reference(ours, tmp_path / "ref" / "hours_1_to_2.hdf5")
    with open_dataset(ref_file) as ds:
        press_frames = [np.flatnonzero((ds.press_id == p) & ds.contact) for p in range(6)]
    torch.manual_seed(0)
    net = UNet(ModelConfig(frames=SPAN, width=8))
    ckpt = reference_training_dict(net, 64)
    ckpt["train_indices"] = np.concatenate([press_frames[p] for p in (0, 2, 3, 5)]).tolist()
    ckpt["test_indices"] = np.concatenate([press_frames[p] for p in (1, 4)]).tolist()
    ckpt["dataset_path"] = "/home/someone/data/hours_1_to_2.hdf5"
    torch.save(ckpt, tmp_path / "ref.pt")
    assert sorted(p.name for p in ref_file.parent.iterdir()) == ["hours_1_to_2.hdf5"]
    return ref_file, tmp_path / "ref.pt", ckpt


def test_reference_checkpoint_is_scored_on_its_own_test_frames(reference_setup, capsys):
    ref_file, ckpt_path, ckpt = reference_setup
    model = load_checkpoint(ckpt_path)
    assert model.meta.training["test_indices"] == ckpt["test_indices"]
    metrics = evaluate(model, ref_file, EvaluateConfig(split="test", device="cpu", progress=False))
    assert metrics["split_source"] == "reference checkpoint test_indices"
    assert metrics["frames"] == len(ckpt["test_indices"]) == metrics["valid_frames"]
    assert metrics["presses"] == 2 and metrics["coverage"] == 1.0
    out = ref_file.parent / "eval"
    code = main(
        [
            "evaluate",
            "--checkpoint",
            str(ckpt_path),
            "--data",
            str(ref_file),
            "--split",
            "test",
            "--out",
            str(out),
            "--device",
            "cpu",
            "--no-plots",
            "--no-progress",
            "--baselines",
        ]
    )
    assert code == 0
    assert "test split (reference checkpoint test_indices)" in capsys.readouterr().out
    with open(out / "metrics.json") as f:
        saved = json.load(f)
    assert saved["frames"] == len(ckpt["test_indices"])


def test_reference_split_is_refused_on_another_dataset(reference_setup, make_dataset, tmp_path):
    ref_file, ckpt_path, ckpt = reference_setup
    model = load_checkpoint(ckpt_path)
    renamed = ref_file.with_name("some_other_hour.hdf5")
    renamed.write_bytes(ref_file.read_bytes())
    with pytest.raises(
        EvaluationError,
        match=r"--split test refused .* are frames of "
        r"/home/someone/data/hours_1_to_2\.hdf5, not of some_other_hour",
    ):
        evaluate(model, renamed, EvaluateConfig(split="test", device="cpu", progress=False))
    short = make_dataset(presses=2, frames_per_press=40, name="other/hours_1_to_2.hdf5")
    with pytest.raises(EvaluationError, match=r"reach frame \d+, and .* has 80 frames"):
        evaluate(model, short, EvaluateConfig(split="test", device="cpu", progress=False))
    with pytest.raises(EvaluationError, match="stores no validation split"):
        evaluate(model, ref_file, EvaluateConfig(split="val", device="cpu", progress=False))
    settings = EvaluateConfig(split="all", device="cpu", progress=False, max_frames=8)
    assert evaluate(model, ref_file, settings)["split_source"] == "all"  # any frames do
    torch.save({k: v for k, v in ckpt.items() if k != "test_indices"}, tmp_path / "old.pt")
    with pytest.raises(EvaluationError, match="no usable train_indices/test_indices"):
        evaluate(
            tmp_path / "old.pt",
            ref_file,
            EvaluateConfig(split="test", device="cpu", progress=False),
        )
