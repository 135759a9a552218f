"""``beadsight demo`` end to end through the real CLI, at a small size."""

from __future__ import annotations

import json

import h5py
import pytest

from beadsight.assets import shipped_model_path
from beadsight.checkpoint import CheckpointError, load_checkpoint
from beadsight.cli import main
from beadsight.demo import TRAIN_DEMO_SEED, training_simulation

REPORT_FILES = (
    "index.html",
    "demo.json",
    "metrics.json",
    "predictions.h5",
    "animation.gif",
    "examples.png",
    "force_traces.png",
    "region_error.png",
    "force_scatter.png",
    "force_error.png",
    "presses.csv",
)


def test_demo_with_a_checkpoint(tmp_path, tiny_model, capsys):
    checkpoint = tiny_model.save(tmp_path / "tiny.pt")
    out = tmp_path / "report"
    argv = ["demo", "--checkpoint", str(checkpoint), "--out", str(out), "--no-progress"]
    argv += "--presses 2 --max-frames 24 --animation-frames 12".split()
    assert main(argv) == 0
    printed = capsys.readouterr().out
    for row in (
        "pressure MAE (kPa)",
        "total-force error (%)",
        "contact IoU",
        "paper",
        "baseline: zero",
        "baseline: mean_gt",
    ):
        assert row in printed
    assert "0.790" in printed  # the paper's MAE beside this run's
    for name in REPORT_FILES:
        assert (out / name).is_file(), name
    # the held-out data the log, metrics.json and the page name is kept, and linked
    assert (out / "heldout.h5").is_file()
    summary = json.loads((out / "demo.json").read_text())
    assert summary["seed"] == 90_210 and summary["frames_evaluated"] == 24
    assert summary["sim_config"]["image_size_px"] == 64  # the model's size
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 24 and "baselines" in metrics
    assert metrics["dataset"] == str(out / "heldout.h5")
    assert len(metrics["per_press"]) == 2 and sum(r["frames"] for r in metrics["per_press"]) == 24
    html = (out / "index.html").read_text()
    assert "animation.gif" in html and "pressure MAE" in html
    assert 'href="heldout.h5"' in html and "Per press" in html
    # Running again into the same report folder replaces it.
    again = [
        "demo",
        "--checkpoint",
        str(checkpoint),
        "--out",
        str(out),
        "--presses",
        "1",
        "--max-frames",
        "4",
        "--animation-frames",
        "2",
        "--no-keep-data",
        "--no-progress",
    ]
    assert main(again) == 0
    assert not (out / "heldout.h5").exists()  # --no-keep-data deletes it
    assert json.loads((out / "demo.json").read_text())["frames_evaluated"] == 4


def test_demo_with_a_rest_referenced_checkpoint(tmp_path, rest_run, capsys):
    """A rest-referenced model runs the whole demo: evaluation and animation give each
    input its rest image from the simulated recording."""
    out = tmp_path / "report"
    argv = ["demo", "--checkpoint", str(rest_run[1]), "--out", str(out), "--no-progress"]
    assert main(argv + "--presses 1 --max-frames 24 --animation-frames 12".split()) == 0
    assert "pressure MAE (kPa)" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["model_config"]["rest_input"] is True and metrics["frames"] == 24
    with h5py.File(out / "predictions.h5", "r") as f:
        assert f.attrs["rest_source"] == "dataset"
    assert (out / "animation.gif").stat().st_size > 0


def test_demo_refuses_a_foreign_folder(tmp_path, tiny_model, capsys):
    checkpoint = tiny_model.save(tmp_path / "tiny.pt")
    foreign = tmp_path / "stuff"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("keep me")
    assert main(["demo", "--checkpoint", str(checkpoint), "--out", str(foreign)]) == 1
    err = capsys.readouterr().err
    assert str(foreign) in err and "not a beadsight demo report" in err
    assert (foreign / "thesis.tex").read_text() == "keep me"


def test_shipped_model_is_found_or_named():
    try:
        path = shipped_model_path()
    except CheckpointError as e:
        assert "sim_model.pt" in str(e) and "--checkpoint" in str(e)
    else:
        assert path.is_file() and path.name == "sim_model.pt"


def test_missing_checkpoint_is_a_clear_error(tmp_path, capsys):
    missing = tmp_path / "nope.pt"
    assert main(["demo", "--checkpoint", str(missing), "--out", str(tmp_path / "r")]) == 1
    assert str(missing) in capsys.readouterr().err


@pytest.mark.slow
def test_demo_train_from_scratch(tmp_path, capsys):
    out = tmp_path / "trained"
    argv = ["demo", "--train", "--out", str(out), "--no-progress"]
    argv += "--presses 1 --max-frames 12 --animation-frames 4".split()
    argv += "--train-presses 3 --train-steps 3 --train-batch-size 2 --train-width 4".split()
    argv += "--train-image-size 32".split()
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "pressure MAE (kPa)" in printed and "would take" in printed
    summary = json.loads((out / "demo.json").read_text())
    estimate = summary["full_run_estimate"]
    assert estimate["measured_steps"] == 3 and estimate["planned_steps"] > 10_000
    assert estimate["reference_size_hours"] > 0
    assert (out / "run" / "best.pt").is_file() and (out / "animation.gif").is_file()
    # The training data is kept; the report draws the run's learning curve (3 logged steps).
    assert (out / "train.h5").is_file() and (out / "heldout.h5").is_file()
    assert summary["files"]["training_curve"] == "training_curve.png"
    assert (out / "training_curve.png").stat().st_size > 0
    assert "Learning curve of the training run" in (out / "index.html").read_text()
    seeds, trained_on = training_simulation(load_checkpoint(out / "run" / "best.pt"))
    assert seeds == {TRAIN_DEMO_SEED} and trained_on["image_size_px"] == 32
