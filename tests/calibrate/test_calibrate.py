"""``beadsight calibrate`` end to end on tiny data (our layout and the reference's), its
outputs, and the clear error of each bad input."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight import load_checkpoint
from beadsight.calibrate.align import fit_force_gain
from beadsight.calibrate.config import CalibrateConfig
from beadsight.calibrate.run import calibrate
from beadsight.cli import main
from beadsight.config import ConfigError, SensorGeometry
from beadsight.data.dataset import DatasetError, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.reference_file import export_reference
from beadsight.data.rest import (
    RestFileError,
    RestReference,
    average_rest,
    load_rest_file,
    rest_ends,
    with_rest,
)
from beadsight.data.splits import dataset_window_ends
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.geometry import total_force_n

QUICK = ["--budget-min", "0.1", "--no-progress"]
# Too short to score the test presses (and draw their figures), which a claim about which
# candidates ran does not look at; it still aligns, chooses and writes model.pt and the report.
BRIEF = ["--budget-min", "0.05", "--no-progress"]


def cli(*args) -> int:
    return main(["calibrate", *map(str, args)])


@pytest.fixture
def base(tiny_model, tmp_path):
    """A 64 px, width-8, 15-frame base model (untrained: calibration must do the work)."""
    return tiny_model.save(tmp_path / "base.pt")


def test_calibrate_cli_with_the_default_base_writes_model_metrics_report(
    make_dataset, tmp_path, capsys
):
    data = make_dataset(presses=6, frames_per_press=80)  # 16 unloaded frames: a rest image
    out = tmp_path / "cal"
    # the shipped base (width 16) needs a few seconds of its budget for its evaluations
    assert cli("--data", data, "--out", out, "--budget-min", "0.3", "--no-progress") == 0
    printed = capsys.readouterr().out
    assert "zero-shot" in printed and "kept:" in printed and "report.html" in printed
    for name in ("model.pt", "aligned.pt", "metrics.json", "report.html", "learning_curve.png"):
        assert (out / name).is_file(), name
    for name in ("presses.csv", "force_scatter.png", "force_error.png"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["candidates"]) == {"zero-shot", "zero-press", "decoder", "all", "scratch"}
    assert metrics["split"] == "held-out" and metrics["presses"] == 1
    assert 0 < metrics["coverage"] <= metrics["window_coverage"]
    record = metrics["calibration"]
    assert record["base"].endswith("base_model.pt") and record["force_gain"] == 1.0
    assert record["alignment"]["frames"].startswith("pre-contact")
    assert len(record["presses"]["train"]) == 4
    # 18 s cannot buy the width-16 base a fine-tuning on this machine: said plainly
    if not record["fine_tuned"]:
        assert "no fine-tuning happened (0 steps)" in record["no_fine_tuning"]
        assert "No fine-tuning happened" in printed
    # the kept fine-tuning's curve (2+ validations), and none without a fine-tuning
    assert (out / "training_curve.png").is_file() == (
        metrics["chosen"] in ("decoder", "all", "scratch")
    )
    assert record["budget"]["seconds"] <= 0.3 * 60 * 1.1
    page = (out / "report.html").read_text()
    for text in ("base model, zero-shot", "zero-press", "Learning curve", "paper"):
        assert text in page
    # model.pt is a normal checkpoint whose stored split evaluate reuses (on the frames
    # calibrate had time to score: as many as its budget left, spread evenly)
    model = load_checkpoint(out / "model.pt")
    assert model.meta.provenance["source"] == "beadsight calibrate"
    again = evaluate(
        out / "model.pt",
        data,
        EvaluateConfig(split="test", max_frames=metrics["max_frames"], progress=False, plots=False),
    )
    assert again["split_source"] == "checkpoint" and again["frames"] == metrics["frames"]
    assert again["mae_kpa"] == pytest.approx(metrics["mae_kpa"], rel=1e-5)
    # a second calibration into the same folder needs --overwrite
    assert cli("--data", data, "--out", out, *QUICK) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert (
        cli("--data", data, "--out", out, "--candidates", "zero-press", "--overwrite", *BRIEF) == 0
    )
    assert not (out / "train").exists()
    again = json.loads((out / "metrics.json").read_text())
    assert again["calibration"]["fine_tuned"] is False
    assert again["candidates"]["decoder"]["status"] == "skipped: not in --candidates"


def test_calibrate_a_reference_layout_file_with_rest_frames_and_gain(make_dataset, base, tmp_path):
    ours = make_dataset(presses=8, frames_per_press=40)
    reference = export_reference(ours, tmp_path / "reference.h5")  # BGR, grams, no presses
    rest = RestReference(np.full((64, 64, 3), 90, np.uint8), frames=30).save(tmp_path / "r.npz")
    config = CalibrateConfig(
        data=str(reference),
        out=str(tmp_path / "cal"),
        base=str(base),
        budget_min=0.25,
        rest=str(rest),
        gain=True,
        skip=1,
        progress=False,
    )
    metrics = calibrate(config)
    record = metrics["calibration"]
    assert record["alignment"]["count"] == 30 and record["alignment"]["pixel_mean"] == [90.0] * 3
    assert record["alignment"]["source"] == str(rest)
    assert load_checkpoint(tmp_path / "cal" / "aligned.pt").meta.pixel_mean == [90.0] * 3
    assert 0.2 <= record["force_gain"] <= 5.0
    used = sorted(sum(record["presses"].values(), []))
    assert used == list(range(1, 8))  # --skip 1 dropped press 0
    model = load_checkpoint(tmp_path / "cal" / "model.pt")
    kept = {"zero-shot": base, "zero-press": tmp_path / "cal" / "aligned.pt"}.get(
        metrics["chosen"], tmp_path / "cal" / "train" / metrics["chosen"] / "best.pt"
    )
    assert model.meta.pixel_mean == load_checkpoint(kept).meta.pixel_mean
    assert model.meta.output_scale_kpa == pytest.approx(
        load_checkpoint(kept).meta.output_scale_kpa * record["force_gain"]
    )
    assert load_rest_file(tmp_path / "cal" / "rest.npz", 64).frames == 30
    assert (tmp_path / "cal" / "report.html").is_file()


def _rest_file(path, frames: int, level: int, image_size: int = 64):
    g = SensorGeometry(image_size_px=image_size)
    with DatasetWriter(path, g) as w:
        w.append(
            np.full((frames, image_size, image_size, 3), level, np.uint8),
            np.zeros(frames),
            np.zeros((frames, 2)),
            np.ones(frames, bool),
            1.7e9 + np.arange(frames) / 30.0,
        )
    return path


def test_bad_inputs_get_clear_errors(make_dataset, base, tmp_path, capsys):
    def run(data, **kw):
        cfg = CalibrateConfig(data=str(data), out=str(tmp_path / "out"), base=str(base), **kw)
        return calibrate(cfg)

    few = make_dataset(presses=2, name="few.h5")
    with pytest.raises(DatasetError, match=r"few\.h5: 2 presses .* at least 3 \(one each"):
        run(few)
    six = make_dataset(presses=6, name="six.h5")
    with pytest.raises(
        DatasetError, match=r"1 presses .* --skip 5\); calibration needs at least 3"
    ):
        run(six, skip=5)
    untouched = _rest_file(tmp_path / "untouched.h5", frames=40, level=100)
    with pytest.raises(DatasetError, match=r"untouched\.h5: no contact frames \(field 'force'"):
        run(untouched)
    small = make_dataset(presses=6, image_size=32, name="small.h5")
    with pytest.raises(ConfigError, match=r"image size 32 px of .*small\.h5 does not fit"):
        run(small)
    junk = tmp_path / "junk.h5"
    junk.write_text("not HDF5")
    with pytest.raises(DatasetError, match="junk.h5"):
        run(junk)
    fieldless = tmp_path / "fieldless.h5"
    with h5py.File(fieldless, "w") as f:
        f["images"] = np.zeros((4, 64, 64, 3), np.uint8)
    with pytest.raises(DatasetError, match=r"fieldless\.h5.*force"):
        run(fieldless)
    with pytest.raises(RestFileError, match=r"rest file .*rest\.h5: "):
        run(six, rest=str(_rest_file(tmp_path / "rest.h5", frames=5, level=1)))
    with pytest.raises(RestFileError, match=r"rest file .*missing\.npz: not found"):
        run(six, rest=str(tmp_path / "missing.npz"))
    small_rest = RestReference(np.zeros((32, 32, 3), np.uint8)).save(tmp_path / "small.npz")
    with pytest.raises(RestFileError, match=r"small\.npz: the image is 32x32 px but the model"):
        run(six, rest=str(small_rest))
    assert not (tmp_path / "out" / "model.pt").exists()
    # the command line prints each as one line, exit code 1
    capsys.readouterr()
    assert cli("--data", few, "--out", tmp_path / "out", "--base", base, *QUICK) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "at least 3" in err


# --- rest-referenced base models -------------------------------------------------------
def test_calibrate_a_rest_referenced_base(rest_run, tmp_path):
    """A rest-referenced base is aligned (its force gain) and its candidates are scored on
    inputs with their rest images (the dataset rule); what is written stays rest-referenced.
    (--skip 1: press 0 has no rest image before it. A 15 s budget leaves no time to
    fine-tune: that needs 30 s a candidate.)"""
    data, base = rest_run
    out = tmp_path / "cal"
    config = CalibrateConfig(
        data=str(data),
        out=str(out),
        base=str(base),
        budget_min=0.25,
        gain=True,
        skip=1,
        device="cpu",
        progress=False,
    )
    metrics = calibrate(config)
    record = metrics["calibration"]
    assert 0.2 <= record["force_gain"] <= 5.0
    for name in ("model.pt", "aligned.pt"):
        assert load_checkpoint(out / name).meta.model.rest_input, name
    with open_dataset(data) as ds:
        frames = dataset_window_ends(ds, 3, record["presses"]["test"], rest=True).size
    assert 0 < metrics["frames"] <= frames
    scored = [c["test"]["frames"] for c in metrics["candidates"].values() if c["test"]]
    assert set(scored) == {metrics["frames"]}  # every candidate on the same test frames


def test_force_gain_of_a_rest_model_uses_inputs_with_their_rest_images(rest_run):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    presses = np.array([2, 3, 4, 5])
    with open_dataset(data) as ds:
        ends = dataset_window_ends(ds, 3, presses, rest=True)
        ends = ends[ds.contact[ends]]
        rests = rest_ends(ds.force_n, ds.valid)[ends]
        inputs = np.stack(
            [
                with_rest(average_rest(ds.read_frames(r - 7, r + 1)), ds.read_frames(e - 2, e + 1))
                for e, r in zip(ends.tolist(), rests.tolist(), strict=True)
            ]
        )
        pred = total_force_n(model.predict(inputs), ds.geometry)
        true = ds.force_n[ends]
    expected = float(np.clip(np.dot(pred, true) / np.dot(pred, pred), 0.2, 5.0))
    assert fit_force_gain(model, str(data), presses) == pytest.approx(expected, rel=1e-5)
