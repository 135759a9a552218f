"""beadsight evaluate: end to end through the CLI, split handling, bad input."""

from __future__ import annotations

import json
import logging
import shutil

import h5py
import numpy as np
import pytest
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel, load_checkpoint
from beadsight.cli import main
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.dataset import DatasetError, dataset_fingerprint, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.labels import label_maps
from beadsight.data.rest import REST_FRAMES, average_rest, rest_ends, with_rest
from beadsight.data.splits import dataset_window_ends, split_presses, window_ends
from beadsight.data.windows import resize_frames
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import EvaluationError, evaluate, select_split
from beadsight.geometry import total_force_n
from beadsight.report.animation import animation_frames, strongest_press

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # a shared 2-core machine
REQUIRED_KEYS = {
    "mae_kpa",
    "force_error_pct",
    "cop_error_mm",
    "iou",
    "region_mae_kpa",
    "worst_region_mae_kpa",
    "frames",
    "force_frames",
    "cop_frames",
    "iou_frames",
    "split",
    "checkpoint",
    "dataset",
}


def refuse_constant(token):
    raise AssertionError(f"metrics.json holds the non-JSON constant {token}")


@pytest.fixture
def model_file(tiny_model, tmp_path):
    return tiny_model.save(tmp_path / "model.pt")


def test_cli_evaluate_end_to_end(make_dataset, model_file, tmp_path, capsys):
    data = make_dataset()
    out = tmp_path / "eval"
    code = main(
        [
            "evaluate",
            "--checkpoint",
            str(model_file),
            "--data",
            str(data),
            "--split",
            "all",
            "--out",
            str(out),
            "--batch-size",
            "16",
            "--device",
            "cpu",
            "--max-frames",
            "60",
            "--baselines",
            "--no-progress",
        ]
    )
    assert code == 0
    captured = capsys.readouterr()
    assert "frame/s" not in captured.err  # --no-progress: no bar in a script's log
    printed = captured.out
    assert "this run" in printed and "paper" in printed and "baseline: zero" in printed
    assert "0.790" in printed and "11.9" in printed and "1.18" in printed

    text = (out / "metrics.json").read_text()
    metrics = json.loads(text, parse_constant=refuse_constant)
    assert REQUIRED_KEYS <= metrics.keys()
    assert metrics["frames"] == 60 and metrics["split"] == "all"
    assert metrics["checkpoint"] == str(model_file) and metrics["dataset"] == str(data)
    assert 0.0 <= metrics["iou"] <= 1.0
    region = metrics["region_mae_kpa"]
    assert len(region) == 4 and all(len(row) == 4 for row in region)
    cells = [v for row in region for v in row if v is not None]
    assert cells and metrics["worst_region_mae_kpa"] == pytest.approx(max(cells))
    assert any(v is None for row in region for v in row)  # 6 presses cover few cells
    assert metrics["presses"] == 6  # --max-frames spreads over the whole split

    with open_dataset(data) as ds, h5py.File(out / "predictions.h5", "r") as f:
        all_ends = window_ends(ds.press_id, ds.valid, 15)
        expected_index = all_ends[np.linspace(0, all_ends.size - 1, 60).round().astype(int)]
        assert expected_index[0] == all_ends[0] and expected_index[-1] == all_ends[-1]
        np.testing.assert_array_equal(f["index"][()], expected_index)
        for name in ("pred_kpa", "gt_kpa"):
            assert f[name].shape == (60, 64, 64) and f[name].dtype == np.float32
            assert f[name].compression == "gzip"
        for name in ("force_gt_n", "force_pred_n"):
            assert f[name].shape == (60,)
        assert f["cop_gt_mm"].shape == f["cop_pred_mm"].shape == (60, 2)
        gt = f["gt_kpa"][()]
        pred = f["pred_kpa"][()]
        i = expected_index
        np.testing.assert_allclose(
            gt, label_maps(ds.force_n[i], ds.position_mm[i], ds.contact[i], ds.geometry)
        )
        np.testing.assert_allclose(
            f["force_gt_n"][()], total_force_n(gt.astype(float), ds.geometry)
        )
    # The stored maps reproduce the reported metrics.
    mae = np.abs(pred.astype(np.float64) - gt).mean(axis=(1, 2)).mean()
    assert metrics["mae_kpa"] == pytest.approx(mae, rel=1e-6)
    zero = metrics["baselines"]["zero"]
    assert zero["mae_kpa"] == pytest.approx(gt.mean(dtype=np.float64), rel=1e-6)
    assert zero["iou"] == 0.0 and zero["force_error_pct"] == pytest.approx(100.0)
    assert "mean_gt" in metrics["baselines"]
    for png in ("examples.png", "region_error.png", "force_traces.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    assert not list(out.glob("*.partial"))


def test_evaluate_uses_checkpoint_split(make_dataset, tiny_model, caplog):
    data = make_dataset()
    with open_dataset(data) as ds:
        fingerprint = dataset_fingerprint(ds)
    # meta.training as beadsight.train.trainer writes it
    tiny_model.meta.training.update(
        split={"train": [0, 1, 2, 3], "val": [4], "test": [5]},
        dataset_fingerprint=fingerprint,
        split_fractions=[0.7, 0.1, 0.2],
        split_seed=0,
    )
    with caplog.at_level(logging.WARNING, logger="beadsight.evaluation.evaluate"):
        metrics = evaluate(
            tiny_model, data, EvaluateConfig(split="test", device="cpu", progress=False)
        )
    assert not caplog.records
    assert metrics["split_source"] == "checkpoint" and metrics["presses"] == 1
    with open_dataset(data) as ds:
        assert metrics["frames"] == len(window_ends(ds.press_id, ds.valid, 15, [5]))
    assert "baselines" not in metrics and "files" not in metrics


def test_split_recomputed_with_warning(make_dataset, tiny_model, caplog):
    data = make_dataset()
    with open_dataset(data) as ds:
        with caplog.at_level(logging.WARNING, logger="beadsight.evaluation.evaluate"):
            sel = select_split(tiny_model, ds, "test")
        assert "no press split" in caplog.text
        assert sel.source == "recomputed"
        np.testing.assert_array_equal(sel.press_ids, split_presses(6)["test"])
        # A split made for another dataset is not trusted.
        tiny_model.meta.training["split"] = {
            "train": list(range(8)),
            "val": [8],
            "test": [9],
            "num_presses": 10,
            "fractions": [0.5, 0.25, 0.25],
            "seed": 3,
        }
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="beadsight.evaluation.evaluate"):
            sel = select_split(tiny_model, ds, "val")
        assert "10 presses" in caplog.text
        np.testing.assert_array_equal(sel.press_ids, split_presses(6, (0.5, 0.25, 0.25), 3)["val"])
        # Same number of presses, but another dataset's fingerprint.
        tiny_model.meta.training.update(
            split={"train": [0, 1, 2, 3], "val": [4], "test": [5]},
            dataset_fingerprint="0123456789abcdef",
            dataset_path="/data/other.h5",
            split_fractions=[0.5, 0.25, 0.25],
            split_seed=1,
        )
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="beadsight.evaluation.evaluate"):
            sel = select_split(tiny_model, ds, "test")
        assert "/data/other.h5" in caplog.text and "fingerprint" in caplog.text
        assert sel.source == "recomputed"
        np.testing.assert_array_equal(sel.press_ids, split_presses(6, (0.5, 0.25, 0.25), 1)["test"])
        everything = select_split(tiny_model, ds, "all")
        np.testing.assert_array_equal(everything.press_ids, np.arange(6))
        with pytest.raises(EvaluationError, match="--split 'train'"):
            select_split(tiny_model, ds, "train")


def test_image_size_mismatch(make_dataset, model_file):
    data = make_dataset(image_size=32)
    with pytest.raises(EvaluationError, match="image_size") as err:
        evaluate(model_file, data, EvaluateConfig(split="all", device="cpu", progress=False))
    assert str(model_file) in str(err.value) and str(data) in str(err.value)
    assert "64" in str(err.value) and "32" in str(err.value)


def test_window_mismatch(make_dataset, model_file, tmp_path, capsys):
    # 10 frames in all: no frame has 15 frames of history (windows may cross presses,
    # so a longer recording of short presses would do)
    data = make_dataset(presses=1, frames_per_press=10)
    with pytest.raises(EvaluationError, match="needs 15 consecutive valid frames") as err:
        evaluate(model_file, data, EvaluateConfig(split="all", device="cpu", progress=False))
    assert str(model_file) in str(err.value) and str(data) in str(err.value)
    code = main(
        [
            "evaluate",
            "--checkpoint",
            str(model_file),
            "--data",
            str(data),
            "--split",
            "all",
            "--out",
            str(tmp_path / "e"),
        ]
    )
    assert code == 1
    assert "window" in capsys.readouterr().err
    assert not (tmp_path / "e" / "metrics.json").exists()


def test_dataset_without_presses(tmp_path, model_file):
    geometry = SensorGeometry(image_size_px=64)
    path = tmp_path / "idle.h5"
    with DatasetWriter(path, geometry) as w:
        n = 30
        frames = np.full((n, 64, 64, 3), 100, np.uint8)
        w.append(frames, np.zeros(n), np.zeros((n, 2)), np.ones(n, bool), np.arange(n) / 30)
    with pytest.raises(DatasetError, match="no presses") as err:
        evaluate(model_file, path, EvaluateConfig(split="all", device="cpu", progress=False))
    assert str(path) in str(err.value)


def test_empty_split(make_dataset, model_file):
    data = make_dataset(presses=2)  # 70/10/20 of 2 presses: no validation press
    with pytest.raises(EvaluationError, match="'val' split has no presses"):
        evaluate(model_file, data, EvaluateConfig(split="val", device="cpu", progress=False))


def test_bad_arguments(make_dataset, model_file, tmp_path):
    data = make_dataset(presses=3, frames_per_press=30)
    with pytest.raises(EvaluationError, match="--max-frames"):
        evaluate(model_file, data, EvaluateConfig(max_frames=0, progress=False))
    with pytest.raises(EvaluationError, match="--batch-size"):
        evaluate(model_file, data, EvaluateConfig(batch_size=0, progress=False))
    with pytest.raises(DatasetError, match="not found"):
        evaluate(model_file, tmp_path / "missing.h5", EvaluateConfig(progress=False))


def test_resize_to_checkpoint_size(make_dataset, tmp_path):
    """A checkpoint trained at 32 px (train --image-size 32) on 64 px data, with --resize."""
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(frames=15, width=8),
        geometry=SensorGeometry(image_size_px=32),
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=10.0,
    )
    model = PressureModel.create(meta)
    data = make_dataset(presses=3, frames_per_press=30)
    with pytest.raises(EvaluationError, match="--resize"):
        evaluate(model, data, EvaluateConfig(split="all", device="cpu", progress=False))
    out = tmp_path / "e"
    metrics = evaluate(
        model,
        data,
        EvaluateConfig(
            split="all", device="cpu", resize=True, max_frames=20, plots=False, progress=False
        ),
        out,
    )
    assert metrics["image_size"] == 32 and metrics["frames"] == 20
    with open_dataset(data) as ds, h5py.File(out / "predictions.h5", "r") as f:
        assert f["pred_kpa"].shape == (20, 32, 32)
        i = f["index"][()]
        small = ds.geometry.with_image_size(32)
        gt = label_maps(ds.force_n[i], ds.position_mm[i], ds.contact[i], small)
        np.testing.assert_allclose(f["gt_kpa"][()], gt)
        frames = resize_frames(ds.read_frames(int(i[0]) - 14, int(i[0]) + 1), 32)
        np.testing.assert_allclose(f["pred_kpa"][0], model.predict(frames), rtol=1e-5, atol=1e-5)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_evaluate_on_cuda_matches_cpu(make_dataset, tiny_model):
    data = make_dataset(presses=3, frames_per_press=30)
    on_cpu = evaluate(tiny_model, data, EvaluateConfig(split="all", device="cpu", progress=False))
    on_gpu = evaluate(tiny_model, data, EvaluateConfig(split="all", device="cuda", progress=False))
    assert on_gpu["device"].startswith("cuda")
    for key in ("mae_kpa", "force_error_pct", "cop_error_mm", "iou"):
        assert on_gpu[key] == pytest.approx(on_cpu[key], rel=1e-3, abs=1e-4), key


# --- rest-referenced models and old checkpoints ---------------------------------------
def _rest_input(ds, end: int, span: int) -> np.ndarray:
    """A rest model's input built by hand: the rest image of data.rest's rule, then the
    window (frames at the dataset's size)."""
    r = int(rest_ends(ds.force_n, ds.valid)[end])
    assert r >= 0
    rest = average_rest(ds.read_frames(r - REST_FRAMES + 1, r + 1))
    return with_rest(rest, ds.read_frames(end - span + 1, end + 1))


def test_a_rest_model_is_scored_on_inputs_with_their_rest_images(rest_run, tmp_path):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    assert model.rest and model.span == 3
    out = tmp_path / "eval"
    metrics = evaluate(
        checkpoint,
        data,
        EvaluateConfig(
            split="all", device="cpu", plots=False, report=False, baselines=True, progress=False
        ),
        out,
    )
    assert metrics["model_config"]["rest_input"] is True
    with open_dataset(data) as ds, h5py.File(out / "predictions.h5", "r") as f:
        assert f.attrs["rest_source"] == "dataset"
        index = f["index"][()]
        np.testing.assert_array_equal(index, dataset_window_ends(ds, 3, rest=True))
        assert not (ds.press_id[index] == 0).any()  # press 0 has no rest image before it
        assert (rest_ends(ds.force_n, ds.valid)[index] >= 0).all()
        inputs = np.stack([_rest_input(ds, e, 3) for e in index.tolist()])
        np.testing.assert_allclose(f["pred_kpa"][()], model.predict(inputs), rtol=1e-5, atol=1e-5)
        # the rest image matters: another rest image (the window's first frame) predicts else
        other = inputs.copy()
        other[:, 0] = inputs[:, 1]
        assert np.abs(model.predict(other) - f["pred_kpa"][()]).max() > 1e-3
        covered = index.size / len(ds)
        test_frames = dataset_window_ends(ds, 3, model.meta.training["split"]["test"], rest=True)
    assert metrics["frames"] == index.size and metrics["valid_frames"] == 240
    assert metrics["coverage"] == metrics["window_coverage"] == pytest.approx(covered)
    assert covered < (240 - 2) / 240  # windows without a rest image are not covered
    # the test split is the checkpoint's, its frames those with a rest image
    test = evaluate(checkpoint, data, EvaluateConfig(device="cpu", plots=False, progress=False))
    assert test["split_source"] == "checkpoint" and test["frames"] == test_frames.size
    assert 0 < test["coverage"] < 1


def test_old_checkpoint_figures_are_unchanged(make_dataset, tiny_model, tmp_path):
    """A model without rest input scores what it scored before rest models (figures
    recorded on main at 537f9ef with this fixture), and its predictions are the plain
    windows'."""
    data = make_dataset()
    out = tmp_path / "eval"
    metrics = evaluate(
        tiny_model,
        data,
        EvaluateConfig(
            split="all", device="cpu", plots=False, report=False, baselines=True, progress=False
        ),
        out,
    )
    recorded = {
        "mae_kpa": 4.75911453479191,
        "force_error_pct": 61.19470498421444,
        "cop_error_mm": 10.786484091599457,
        "iou": 0.11826646639595896,
    }
    for key, value in recorded.items():
        assert metrics[key] == pytest.approx(value, rel=1e-5), key
    assert metrics["baselines"]["mean_gt"]["mae_kpa"] == pytest.approx(4.478115269018249)
    assert metrics["frames"] == 226 and metrics["coverage"] == pytest.approx(226 / 240)
    with open_dataset(data) as ds, h5py.File(out / "predictions.h5", "r") as f:
        assert f.attrs["rest_source"] == "none"
        e = int(f["index"][7])
        expected = tiny_model.predict(ds.read_frames(e - 14, e + 1))
        np.testing.assert_allclose(f["pred_kpa"][7], expected, rtol=1e-5, atol=1e-5)


def test_animation_of_a_rest_model_skips_presses_without_a_rest_image(rest_run, tmp_path):
    data = tmp_path / "strong_first.h5"
    shutil.copy(rest_run[0], data)
    with h5py.File(data, "r+") as f:
        f["force"][:40] = f["force"][:40] * 5  # press 0, with no rest before it, is strongest
    model = load_checkpoint(rest_run[1])
    with open_dataset(data) as ds:
        peaks = [ds.force_n[a:b].max() for a, b in ds.presses]
    assert int(np.argmax(peaks)) == 0
    press = strongest_press(data, model)
    assert press == 1 + int(np.argmax(peaks[1:]))
    clip = animation_frames(model, data, press, batch_size=4, count=12)
    with open_dataset(data) as ds:
        index = clip["index"]
        assert index.size == 12 and (ds.press_id[index] == press).all()
        inputs = np.stack([_rest_input(ds, e, 3) for e in index.tolist()])
        np.testing.assert_array_equal(clip["frames"], ds.read_frames_at(index))
    np.testing.assert_allclose(clip["pred"], model.predict(inputs), rtol=1e-5, atol=1e-5)
