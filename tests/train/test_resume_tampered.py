"""Issue 26: `train --resume` with a tampered last.pt is one named error (exit 1), whatever
was changed -- never KeyError, TypeError, ValueError or RuntimeError (exit 70)."""

from __future__ import annotations

import json

import pytest
import torch
from helpers.synthetic_presses import write_synthetic_dataset
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight.cli import main


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("resume")
    data = write_synthetic_dataset(folder / "d.h5", 6, 40, 64, 0, 30.0)
    argv = ["train", "--data", str(data), "--out", str(folder / "run"), "--width", "8"]
    assert main([*argv, "--steps", "2", "--batch-size", "8", "--no-progress"]) == 0
    return folder / "run", (folder / "run" / "last.pt").read_bytes()


def _no_split(state):
    meta = json.loads(state["beadsight"])
    del meta["training"]["split"]
    state["beadsight"] = json.dumps(meta)


def _step_text(state):
    state["step"] = "seven"


def _optimizer(state):
    state["optimizer"] = {"state": {}, "param_groups": [{"params": [0, 1]}]}


def _rng(state):
    state["rng_cpu"] = [torch.zeros(3, dtype=torch.uint8)]


def _moment_shape(state):
    moments = state["optimizer"]["state"][0]
    moments["exp_avg"] = torch.zeros(3)


@pytest.mark.parametrize("tamper", [_no_split, _step_text, _optimizer, _rng, _moment_shape])
def test_a_tampered_last_pt_is_one_named_error(run, tamper, capsys):
    folder, original = run
    last = folder / "last.pt"
    last.write_bytes(original)
    state = torch.load(last, weights_only=False)
    tamper(state)
    torch.save(state, last)
    assert main(["train", "--out", str(folder), "--resume", "--steps", "4", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert f"{last}: the training state cannot be resumed" in err, err
    assert "start a new --out" in err and "internal error" not in err
