"""Training against a wall-clock budget, on part of the presses, with a frozen encoder."""

from __future__ import annotations

import json
import time

import pytest
import torch
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight import load_checkpoint
from beadsight.cli import main
from beadsight.config import ConfigError
from beadsight.train.config import TrainConfig
from beadsight.train.trainer import train

FAST = dict(width=8, batch_size=8, progress=False, frames=15)


def _lines(run):
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def test_budget_stops_the_run_and_the_schedule_spans_it(make_dataset, tmp_path):
    data = make_dataset(presses=8)
    run = tmp_path / "run"
    t0 = time.monotonic()
    config = TrainConfig(
        data=str(data),
        out=str(run),
        epochs=10_000,
        budget_min=0.05,
        val_every_min=0.015,
        lr=1e-3,
        lr_schedule="cosine",
        # half the usual batch: steps short against the budget, so the last one starts late in it
        **{**FAST, "batch_size": 4},
    )
    train(config)
    took = time.monotonic() - t0
    assert took < 0.05 * 60 + 20  # the budget, plus setup and the last step and validation
    lines = _lines(run)
    vals = [x for x in lines if x["event"] == "val"]
    assert len(vals) >= 2  # timed validations, not only at the (never reached) epoch end
    assert lines[-1]["time_s"] >= 0.05 * 60 - 1
    assert lines[-1]["lr"] < 0.2e-3  # the cosine schedule reached (close to) lr_min at the budget
    assert (run / "best.pt").is_file()


def test_presses_skip_and_decoder_only(make_dataset, tmp_path):
    data = make_dataset(presses=8)
    first = tmp_path / "first"
    train(TrainConfig(data=str(data), out=str(first), steps=2, **FAST))
    init = first / "best.pt"
    run = tmp_path / "run"
    config = TrainConfig(
        data=str(data),
        out=str(run),
        steps=3,
        presses=4,
        skip_presses=2,
        init=str(init),
        train_layers="decoder",
        augment=False,
        **FAST,
    )
    train(config)
    split = json.loads((run / "split.json").read_text())
    used = sorted(split["train"] + split["val"] + split["test"])
    assert used == [2, 3, 4, 5]
    before = load_checkpoint(init).module.net.state_dict()
    after = load_checkpoint(run / "last.pt").module.net.state_dict()
    assert torch.equal(before["C1.layer.0.weight"], after["C1.layer.0.weight"])  # encoder fixed
    assert not torch.equal(before["pred.weight"], after["pred.weight"])  # decoder trained


def test_bad_budget_and_layers_are_refused(make_dataset, tmp_path):
    with pytest.raises(ConfigError, match="budget_min"):
        TrainConfig(data="d.h5", out="r", budget_min=0)
    with pytest.raises(ConfigError, match="train_layers"):
        TrainConfig(data="d.h5", out="r", train_layers="encoder")
    data = make_dataset(presses=4)
    with pytest.raises(ConfigError, match="skip_presses 4 leaves no press"):
        train(TrainConfig(data=str(data), out=str(tmp_path / "r"), skip_presses=4, **FAST))


def test_train_cli_takes_a_budget(make_dataset, tmp_path):
    data = make_dataset(presses=6)
    run = tmp_path / "run"
    args = ["train", "--data", str(data), "--out", str(run), "--budget-min", "0.01"]
    assert main([*args, "--width", "8", "--batch-size", "8", "--no-progress"]) == 0
    assert json.loads((run / "config.json").read_text())["budget_min"] == 0.01
