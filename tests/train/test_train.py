"""Training: configuration, the run folder through the real CLI, resume, DDP, bad inputs."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.cli import run_beadsight
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight import load_checkpoint
from beadsight.checkpoint import CheckpointError, read_checkpoint_file
from beadsight.cli import main
from beadsight.config import ConfigError, SensorGeometry
from beadsight.data.dataset import DatasetError, dataset_fingerprint, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.geometry import disk_pressure_kpa
from beadsight.train.config import TrainConfig, resolve_train_config
from beadsight.train.distributed import Distributed
from beadsight.train.prepare import output_scale_kpa
from beadsight.train.run import METRIC_KEYS
from beadsight.train.step import model_inputs
from beadsight.train.trainer import Trainer, train

FAST = ["--width", "8", "--no-progress"]


def cli(*args) -> int:
    return main(["train", *map(str, args)])


def _metrics(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def _optimizer_steps(state: dict) -> set[int]:
    return {int(s["step"]) for s in state["optimizer"]["state"].values()}


# --- configuration ------------------------------------------------------------------
def test_config_precedence_defaults_toml_flags(tmp_path):
    toml = tmp_path / "train.toml"
    toml.write_text("[train]\nwidth = 8\nlr = 5e-4\nsteps = 2\nsplit = [0.6, 0.2, 0.2]\n")
    config = resolve_train_config(
        {"data": "d.h5", "out": str(tmp_path / "r"), "lr": 2e-4, "steps": None}, toml
    )
    assert config.width == 8 and config.steps == 2 and config.split == (0.6, 0.2, 0.2)
    assert config.lr == 2e-4  # the flag beats the file
    assert config.batch_size == 64 and config.weight_decay == 1e-4 and config.dropout == 0.2
    assert config.noise_std == 0.05 and config.precision == "fp32" and config.frames == 15
    toml.write_text("bogus = 1\n")
    with pytest.raises(ConfigError, match="bogus"):
        resolve_train_config({"data": "d.h5", "out": "r"}, toml)
    with pytest.raises(ConfigError, match="data"):
        resolve_train_config({"out": "r"})


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("image_size", 60, "image_size"),
        ("precision", "fp8", "precision"),
        ("split", (0.5, 0.5, 0.5), "split"),
        ("width", 0, "width"),
        ("up_kernel", 2, "up_kernel"),
        ("frame_stride", 0, "frame_stride"),
        ("device", "tpu", "device"),
        ("loader", "disk", "loader"),
        ("batch_size", 0, "batch_size"),
        ("steps", 0, "steps"),
    ],
)
def test_train_config_rejects_bad_values(field, value, match):
    with pytest.raises(ConfigError, match=match):
        TrainConfig(data="d.h5", out="r", **{field: value})
    with pytest.raises(ConfigError, match="fp16"):
        TrainConfig(data="d.h5", out="r", device="cpu", precision="fp16")


def test_output_scale_is_the_reference_avg_pressure():
    g = SensorGeometry()
    force = np.array([4.0, 6.0, 5.0])
    radius_px = g.finger_radius_mm / g.mm_per_px
    reference = disk_pressure_kpa(5.0, g) * math.pi * radius_px**2 / g.image_size_px**2
    assert output_scale_kpa(force, g) == pytest.approx(reference, rel=2e-3)
    # equivalently the mean force spread over the whole field of view
    assert output_scale_kpa(force, g) == pytest.approx(5.0 / (0.041**2) / 1000, rel=2e-3)


def test_input_noise_only_in_training(make_dataset, tmp_path, tiny_model):
    frames = torch.randint(0, 256, (2, 15, 64, 64, 3), dtype=torch.uint8)
    clean = tiny_model.module.normalize(frames)
    assert torch.equal(model_inputs(tiny_model.module, frames), clean)
    noisy = model_inputs(tiny_model.module, frames, 0.05)
    assert (noisy - clean).std().item() == pytest.approx(0.05, rel=0.05)

    data = make_dataset()
    losses, vals = [], []
    for noise in (0.0, 10.0):
        config = TrainConfig(
            data=str(data),
            out=str(tmp_path / f"n{noise}"),
            width=8,
            batch_size=8,
            dropout=0.0,
            noise_std=noise,
            progress=False,
            val_stride=4,
        )
        trainer = Trainer(config, Distributed(), torch.device("cpu"))
        trainer.setup()
        vals.append(trainer.validate())
        # validation is noise-free: it equals the network on clean inputs
        frames, targets = next(iter(trainer.val_loader))
        with torch.no_grad():
            out = trainer.module.eval().net(trainer.module.normalize(frames))[:, 0]
        trainer.module.train()
        assert out.shape == targets.shape
        trainer.train_loader.set_epoch(0)
        losses.append(trainer.train_step(*next(iter(trainer.train_loader))).item())
        trainer.close()
    assert vals[0] == vals[1]  # same init, no noise in validation
    assert losses[0] != pytest.approx(losses[1], rel=1e-3)  # the training step adds noise


# --- end to end through the CLI -----------------------------------------------------
def test_train_cli_writes_a_complete_run_folder(make_dataset, tmp_path, capsys):
    data = make_dataset(frames_per_press=20)  # short presses: one epoch of cheap steps
    run = tmp_path / "run"
    assert cli("--data", data, "--out", run, "--steps", 4, "--batch-size", 20, *FAST) == 0
    assert str(run) in capsys.readouterr().out
    for name in ("config.json", "split.json", "metrics.jsonl", "best.pt", "last.pt"):
        assert (run / name).is_file(), name

    config = json.loads((run / "config.json").read_text())
    assert config["width"] == 8 and config["steps"] == 4 and config["lr"] == 1e-4
    assert config["data"] == str(data.resolve())

    split = json.loads((run / "split.json").read_text())
    with open_dataset(data) as ds:
        assert split["dataset_fingerprint"] == dataset_fingerprint(ds)
        ids = split["train"] + split["val"] + split["test"]
        assert sorted(ids) == list(range(ds.num_presses))  # disjoint, complete
    assert split["fractions"] == [0.7, 0.1, 0.2] and split["seed"] == 0

    lines = _metrics(run)
    assert all(tuple(line) == METRIC_KEYS for line in lines)
    train_lines = [line for line in lines if line["event"] == "train"]
    val_lines = [line for line in lines if line["event"] == "val"]
    assert train_lines[-1]["step"] == 4 and train_lines[-1]["samples_per_s"] > 0
    # every frame of a train press with 14 frames of history ends a window (item 7)
    with open_dataset(data) as ds:
        frames = np.flatnonzero(np.isin(ds.press_id, split["train"]))
        assert split["windows"]["train"] == int((frames >= 14).sum())
    assert split["windows"]["train"] == 80  # train presses 2-5: all have the history
    assert len(val_lines) == 1 and val_lines[0]["epoch"] == 1.0  # 80 windows / 20 = 4 steps
    assert math.isfinite(val_lines[0]["val_loss"]) and val_lines[0]["val_mae_kpa"] > 0

    for name in ("best.pt", "last.pt"):
        model = load_checkpoint(run / name)
        assert model.span == 15 and model.image_size == 64 and model.meta.model.width == 8
        t = model.meta.training
        # named relative to the run folder (issue 26: no absolute paths of this machine)
        assert t["dataset_path"] == os.path.relpath(data.resolve(), run.resolve())
        assert (run / t["dataset_path"]).resolve() == data.resolve()
        assert t["dataset_fingerprint"] == split["dataset_fingerprint"]
        assert t["split"]["test"] == split["test"] and t["split"]["train"] == split["train"]
        assert t["config"]["width"] == 8 and t["step"] == 4 and t["epoch"] == 1
        assert t["best_val"]["val_loss"] == pytest.approx(val_lines[0]["val_loss"])
        with open_dataset(data) as ds:
            kpa = model.predict(ds.read_frames(0, 15))
        assert kpa.shape == (64, 64) and np.isfinite(kpa).all() and (kpa >= 0).all()
    state = read_checkpoint_file(run / "last.pt")  # weights_only
    assert state["step"] == 4 and _optimizer_steps(state) == {4}

    # a second run into the same folder needs --resume
    with pytest.raises(ConfigError, match="--resume"):
        train(TrainConfig(data=str(data), out=str(run), width=8, steps=4))
    # resuming must keep the run's settings and its dataset
    with pytest.raises(CheckpointError, match="'width'"):
        train(TrainConfig(data=str(data), out=str(run), width=16, resume=True, batch_size=32))
    other = make_dataset(seed=5, name="other.h5")
    with pytest.raises(CheckpointError, match="dataset_fingerprint"):
        train(resolve_train_config({"data": str(other), "out": str(run), "resume": True}))
    # the CLI reports such errors as one line naming the field, exit code 1
    assert cli("--data", data, "--out", run, "--resume", "--width", 16) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'width'" in err
    # resuming a finished run with no more steps to do is a no-op
    assert cli("--out", run, "--resume", "--no-progress") == 0
    assert read_checkpoint_file(run / "last.pt")["step"] == 4


def test_train_bf16_at_reduced_image_size_with_host_loader(make_dataset, tmp_path):
    data = make_dataset()
    run = tmp_path / "run"
    args = ["--steps", 2, "--batch-size", 8, "--precision", "bf16", "--image-size", 32]
    assert (
        cli("--data", data, "--out", run, *args, "--loader", "host", "--num-workers", 0, *FAST) == 0
    )
    model = load_checkpoint(run / "last.pt")
    assert model.image_size == 32 and model.geometry.image_size_px == 32
    assert model.geometry.sensor_size_mm == 41.0
    assert model.meta.training["config"]["precision"] == "bf16"
    with open_dataset(data) as ds:
        frames = ds.read_frames(0, 15)
    with pytest.raises(ValueError, match="image_size"):
        model.predict(frames)  # 64 px frames do not fit a 32 px model
    small = np.stack([f[::2, ::2] for f in frames])
    assert model.predict(small).shape == (32, 32)


def test_cosine_schedule_runs_from_lr_to_lr_min():
    config = TrainConfig(data="d.h5", out="r", lr=1e-3, lr_min=1e-5, lr_schedule="cosine")
    assert config.learning_rate(0, 101) == pytest.approx(1e-3)
    assert config.learning_rate(50, 101) == pytest.approx((1e-3 + 1e-5) / 2)
    assert config.learning_rate(100, 101) == pytest.approx(1e-5)
    rates = [config.learning_rate(s, 101) for s in range(101)]
    assert (np.diff(rates) < 0).all()
    assert TrainConfig(data="d.h5", out="r", lr=1e-3).learning_rate(100, 101) == 1e-3
    with pytest.raises(ConfigError, match="lr_schedule"):
        TrainConfig(data="d.h5", out="r", lr_schedule="step")
    with pytest.raises(ConfigError, match="lr_min"):
        TrainConfig(data="d.h5", out="r", lr=1e-4, lr_min=1e-3)


def test_fine_tune_from_a_checkpoint_with_a_cosine_schedule(make_dataset, tmp_path, capsys):
    data = make_dataset()
    base, tuned = tmp_path / "base", tmp_path / "tuned"
    assert cli("--data", data, "--out", base, "--steps", 2, "--batch-size", 8, *FAST) == 0
    source = load_checkpoint(base / "best.pt")

    # the width comes from the checkpoint (the default would be 16); a tiny learning
    # rate leaves the starting weights visible in the result
    args = ["--steps", 3, "--batch-size", 8, "--lr", 1e-12, "--lr-schedule", "cosine"]
    assert (
        cli("--data", data, "--out", tuned, "--init", base / "best.pt", *args, "--no-progress") == 0
    )
    model = load_checkpoint(tuned / "last.pt")
    assert model.meta.model.width == 8
    for name, value in model.module.net.state_dict().items():
        torch.testing.assert_close(value, source.module.net.state_dict()[name], atol=1e-8, rtol=0)
    assert model.meta.pixel_mean == source.meta.pixel_mean
    assert model.meta.output_scale_kpa == source.meta.output_scale_kpa
    init_path = model.meta.provenance["init"]["path"]
    assert init_path == os.path.relpath((base / "best.pt").resolve(), tuned.resolve())
    assert (tuned / init_path).resolve() == (base / "best.pt").resolve()
    lrs = [line["lr"] for line in _metrics(tuned) if line["event"] == "train"]
    assert lrs[-1] == pytest.approx(0.0)  # the last step ran at lr_min
    capsys.readouterr()
    assert main(["info", str(tuned / "last.pt"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["initialised_from"] == init_path  # relative to the run, as recorded
    assert (summary["format"], summary["width"], summary["step"]) == ("beadsight", 8, 3)
    assert summary["parameters"] == sum(p.numel() for p in model.module.parameters())

    # a cosine run's length is part of its schedule: resuming it longer is refused
    assert cli("--out", tuned, "--resume", "--steps", 6) == 1
    assert "'steps'" in capsys.readouterr().err
    # a fully convolutional model carries over to another resolution
    small = tmp_path / "small"
    args = ["--steps", 1, "--batch-size", 8, "--lr", 1e-12, "--image-size", 32, "--no-progress"]
    assert cli("--data", data, "--out", small, "--init", base / "best.pt", *args) == 0
    model = load_checkpoint(small / "last.pt")
    assert model.image_size == 32 and model.geometry.image_size_px == 32
    for name, value in model.module.net.state_dict().items():
        torch.testing.assert_close(value, source.module.net.state_dict()[name], atol=1e-8, rtol=0)

    # the frame stride is not in the weights' shapes: a run may change it, and its
    # windows then span (15 - 1) * 2 + 1 frames
    strided = tmp_path / "strided"
    args = ["--steps", 1, "--batch-size", 8, "--frame-stride", 2, "--no-progress"]
    assert cli("--data", data, "--out", strided, "--init", base / "best.pt", *args) == 0
    model = load_checkpoint(strided / "last.pt")
    assert (model.meta.model.frame_stride, model.frames, model.span) == (2, 15, 29)
    split = json.loads((strided / "split.json").read_text())
    base_split = json.loads((base / "split.json").read_text())
    assert split["frame_stride"] == 2
    # a window needs 28 frames of history instead of 14, whatever press they belong to
    with open_dataset(data) as ds:
        frames = np.flatnonzero(np.isin(ds.press_id, split["train"]))
    assert split["windows"]["train"] == int((frames >= 28).sum())
    assert base_split["windows"]["train"] == int((frames >= 14).sum())

    # an architecture that does not fit the checkpoint names the field
    with pytest.raises(ConfigError, match="width is 8 in the checkpoint but 16"):
        train(TrainConfig(data=str(data), out=str(tmp_path / "w16"), init=str(base / "best.pt")))


# --- bad inputs ---------------------------------------------------------------------
def test_dataset_without_presses_is_refused(tmp_path):
    g = SensorGeometry(image_size_px=64)
    path = tmp_path / "rest.h5"
    n = 40
    with DatasetWriter(path, g) as w:
        w.append(
            np.zeros((n, 64, 64, 3), np.uint8),
            np.zeros(n),
            np.zeros((n, 2)),
            np.ones(n, bool),
            np.arange(n) / 30.0,
        )
    with pytest.raises(DatasetError, match="no presses") as e:
        train(TrainConfig(data=str(path), out=str(tmp_path / "run"), width=8, steps=1))
    assert str(path) in str(e.value)


def test_bad_training_inputs_name_the_field(make_dataset, tmp_path):
    data = make_dataset()
    out = str(tmp_path / "run")
    with pytest.raises(ConfigError, match="split .* train split with no presses"):
        train(TrainConfig(data=str(data), out=out, width=8, steps=1, split=(0.0, 0.5, 0.5)))
    with pytest.raises(ConfigError, match="image_size 128"):
        train(TrainConfig(data=str(data), out=out, width=8, steps=1, image_size=128))
    odd = make_dataset(image_size=60, name="odd.h5")
    with pytest.raises(ConfigError, match="image_size 60"):
        train(TrainConfig(data=str(odd), out=out, width=8, steps=1))
    with pytest.raises(ConfigError, match="frames 50"):  # spans 246 frames; the data has 240
        train(TrainConfig(data=str(data), out=out, width=8, steps=1, frames=50, frame_stride=5))
    with pytest.raises(CheckpointError, match="no checkpoint to resume"):
        train(TrainConfig(data=str(data), out=out, width=8, steps=1, resume=True))
    with pytest.raises(DatasetError, match="missing.h5"):
        train(TrainConfig(data=str(tmp_path / "missing.h5"), out=out, width=8, steps=1))
    assert not (tmp_path / "run" / "last.pt").exists()


# --- killed runs and DDP (subprocesses) --------------------------------------------
def _beadsight(*args) -> list[str]:
    return [sys.executable, "-m", "beadsight", "train", *map(str, args)]


@pytest.mark.slow
def test_resume_after_sigkill_continues_the_same_run(make_dataset, tmp_path):
    data = make_dataset()
    run = tmp_path / "run"
    log = (tmp_path / "first.log").open("w")
    proc = subprocess.Popen(
        _beadsight(
            "--data",
            data,
            "--out",
            run,
            "--steps",
            100_000,
            "--batch-size",
            4,
            "--checkpoint-every-steps",
            3,
            "--threads",
            1,
            *FAST,
        ),
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 180
        while not (run / "last.pt").is_file():
            assert proc.poll() is None, (tmp_path / "first.log").read_text()
            assert time.monotonic() < deadline, "no checkpoint within 180 s"
            time.sleep(0.1)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    killed = read_checkpoint_file(run / "last.pt")
    step = int(killed["step"])
    assert step >= 3 and _optimizer_steps(killed) == {step}
    split_before = json.loads((run / "split.json").read_text())

    # the resumed run needs no child process of its own: the killed one was the point
    result = run_beadsight(
        "train", "--out", run, "--resume", "--steps", step + 3, "--threads", 1, "--no-progress"
    )
    assert result.returncode == 0, result.stderr
    final = read_checkpoint_file(run / "last.pt")
    assert final["step"] == step + 3
    assert _optimizer_steps(final) == {step + 3}  # the optimizer state carried over
    assert json.loads((run / "split.json").read_text()) == split_before
    model = load_checkpoint(run / "last.pt")
    assert model.meta.training["split"]["test"] == split_before["test"]
    assert model.meta.model.width == 8  # settings came from the run's config.json
    steps = [line["step"] for line in _metrics(run) if line["event"] == "train"]
    assert steps == sorted(set(steps)) and steps[-1] == step + 3
    assert json.loads((run / "config.json").read_text())["steps"] == step + 3


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ddp_with_two_gloo_processes(make_dataset, tmp_path):
    """Data-parallel training in two ``beadsight train`` processes (gloo). They start with
    the variables torchrun gives its workers (RANK, LOCAL_RANK, WORLD_SIZE, LOCAL_WORLD_SIZE,
    MASTER_ADDR, MASTER_PORT): all that beadsight and torch's env:// rendezvous read.
    torchrun's launcher itself, one more process importing torch, is not beadsight's code."""
    data = make_dataset()
    run = tmp_path / "run"
    args = _beadsight(
        "--data", data, "--out", run, "--steps", 3, "--batch-size", 8, "--device", "cpu", *FAST
    )
    world = {"WORLD_SIZE": "2", "LOCAL_WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1"}
    env = {**os.environ, **world, "MASTER_PORT": str(_free_port()), "OMP_NUM_THREADS": "1"}
    logs = [(tmp_path / f"rank{rank}.out", tmp_path / f"rank{rank}.err") for rank in range(2)]
    procs = []
    try:
        for rank, (out, err) in enumerate(logs):
            with out.open("w") as stdout, err.open("w") as stderr:
                rank_env = {**env, "RANK": str(rank), "LOCAL_RANK": str(rank)}
                procs.append(subprocess.Popen(args, stdout=stdout, stderr=stderr, env=rank_env))
        # like torchrun, stop at the first failed rank: the other would wait for it
        deadline = time.monotonic() + 300
        while any(p.poll() is None for p in procs) and all(p.poll() in (None, 0) for p in procs):
            assert time.monotonic() < deadline, "the ranks did not finish within 300 s"
            time.sleep(0.1)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
    errors = "\n".join(f"rank {r}: {err.read_text()[-3000:]}" for r, (_, err) in enumerate(logs))
    assert [proc.returncode for proc in procs] == [0, 0], errors
    stdout = [out.read_text() for out, _ in logs]
    assert stdout[0].count("run folder:") == 1 and "run folder:" not in stdout[1]  # rank 0
    state = read_checkpoint_file(run / "last.pt")
    assert state["step"] == 3 and len(state["rng_cpu"]) == 2
    model = load_checkpoint(run / "last.pt")
    assert model.meta.training["world_size"] == 2
    lines = _metrics(run)
    assert [line["event"] for line in lines].count("val") == 1  # written once, by rank 0
    assert (run / "best.pt").is_file()
