"""`beadsight average`: the weighted mean of checkpoints of one model, and what it refuses."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from beadsight.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from beadsight.errors import ConfigError
from beadsight.train.average import average_checkpoints
from tests.helpers.cli import run_beadsight
from tests.helpers.live import tiny_model


def _saved(tmp_path, name, **kwargs):
    model = tiny_model(**kwargs)
    return save_checkpoint(tmp_path / name, model), model.module.net.state_dict()


def test_the_mean_is_weighted_and_says_what_it_averaged(tmp_path):
    a, sa = _saved(tmp_path, "a.pt", seed=1)
    b, sb = _saved(tmp_path, "b.pt", seed=2)
    ran = run_beadsight("average", a, b, "--weights", 3, 1, "--out", tmp_path / "c.pt")
    assert ran.returncode == 0, ran.stderr
    assert "x 0.750" in ran.stdout and "x 0.250" in ran.stdout
    c = load_checkpoint(tmp_path / "c.pt")
    for key, tensor in c.module.net.state_dict().items():
        if tensor.is_floating_point():
            torch.testing.assert_close(tensor, 0.75 * sa[key] + 0.25 * sb[key])
    assert [e["weight"] for e in c.meta.provenance["average"]] == [0.75, 0.25]
    assert c.meta.training == {}
    info = run_beadsight("info", tmp_path / "c.pt")
    assert f"{a} x 0.750" in info.stdout and f"{b} x 0.250" in info.stdout
    again = run_beadsight("average", b, a, "--out", tmp_path / "c.pt")
    assert (
        again.returncode == 1 and "already exists" in again.stderr and "--overwrite" in again.stderr
    )
    assert load_checkpoint(tmp_path / "c.pt").meta.provenance["average"][0]["path"] == str(a)
    assert run_beadsight("average", b, a, "--out", tmp_path / "c.pt", "--overwrite").returncode == 0


def test_equal_weights_by_default(tmp_path):
    a, sa = _saved(tmp_path, "a.pt", seed=1)
    b, sb = _saved(tmp_path, "b.pt", seed=2)
    state = average_checkpoints([a, b]).module.net.state_dict()
    key = next(k for k, v in sa.items() if v.is_floating_point())
    torch.testing.assert_close(state[key], (sa[key] + sb[key]) / 2)


def test_checkpoints_of_different_models_are_refused_by_name(tmp_path):
    a, _ = _saved(tmp_path, "a.pt")
    other_scale, _ = _saved(tmp_path, "scale.pt", scale_kpa=20.0)
    with pytest.raises(CheckpointError, match="scale.pt: its output_scale_kpa differs from"):
        average_checkpoints([a, other_scale])
    wide = tiny_model()
    meta = dataclasses.replace(
        wide.meta, model=dataclasses.replace(wide.meta.model, frames=wide.meta.model.frames + 1)
    )
    other_shape = save_checkpoint(tmp_path / "shape.pt", type(wide).create(meta))
    ran = run_beadsight("average", a, other_shape, "--out", tmp_path / "c.pt")
    assert ran.returncode != 0
    assert "shape.pt: its model differs from" in ran.stderr
    assert not (tmp_path / "c.pt").exists()


@pytest.mark.parametrize(
    ("weights", "message"),
    [
        ([1.0], "1 weights for 2 checkpoints"),
        ([1.0, 0.0], "must be finite and > 0"),
        ([1.0, float("nan")], "finite"),
        ([1.0, float("inf")], "finite"),
    ],
)
def test_bad_weights_are_refused(tmp_path, weights, message):
    a, _ = _saved(tmp_path, "a.pt")
    b, _ = _saved(tmp_path, "b.pt", seed=3)
    with pytest.raises(ConfigError, match=message):
        average_checkpoints([a, b], weights)


def test_one_checkpoint_is_not_an_average(tmp_path):
    a, _ = _saved(tmp_path, "a.pt")
    with pytest.raises(ConfigError, match="at least two checkpoints, got 1"):
        average_checkpoints([a])


def test_info_reads_a_forged_average_record_as_data(tmp_path):
    model = tiny_model()
    junk = [
        {"path": "a.pt", "weight": "1; rm -rf /"},
        "not a record",
        {"path": "b.pt", "weight": 0.5},
    ]
    model.meta = dataclasses.replace(model.meta, provenance={"average": junk})
    path = save_checkpoint(tmp_path / "forged.pt", model)
    info = run_beadsight("info", path)
    assert info.returncode == 0, info.stderr
    assert "b.pt x 0.500" in info.stdout and "rm -rf" not in info.stdout
