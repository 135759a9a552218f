"""Shared fixtures: tiny synthetic datasets and models (64x64 frames, U-Net width 8)."""

from __future__ import annotations

import dataclasses
import faulthandler
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from beadsight.checkpoint import PressureModel
    from beadsight.config import ModelConfig


def _share_cores_among_workers() -> None:
    """Under pytest-xdist, each worker's runtimes get its share of the cores (one thread each
    with one worker per core), through OMP_NUM_THREADS: torch reads it, and so does
    ``beadsight.inference.machine.default_threads`` for ONNX Runtime and OpenVINO; the CLI
    children a test starts inherit it. Without it every worker's runtimes spin on every core:
    with 2 workers on 2 cores at a load of 5-6, tests/inference/test_int8.py took 236 s
    instead of 53 s, test_select.py 112-207 s instead of 35 s. Set before torch and numpy
    load (fixtures import them); a limit the caller set is kept."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if "PYTEST_XDIST_WORKER" not in os.environ or workers < 2 or "OMP_NUM_THREADS" in os.environ:
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    share = max(1, (cores or 1) // workers)
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(name, str(share))


_share_cores_among_workers()
# torch, numpy and beadsight are imported inside the fixtures and hooks below: under xdist the
# controller process loads this file too but runs no test, and importing torch there (3 s)
# delayed every worker's start.


def pytest_configure(config):
    """Let the Ctrl-C tests' children see SIGINT even when pytest runs as a background job.

    A non-interactive shell starts background jobs (``nohup .ci/run &``) with SIGINT ignored,
    and an ignored signal is inherited by every child, so ``beadsight collect`` or
    ``beadsight live`` would never receive the test's Ctrl-C and run to the end.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


pytest_plugins = ("pytester",)  # tests/test_ci_policy.py runs this file's policy on a probe


def pytest_collection_modifyitems(config, items):
    """GPU tests are collected only where a CUDA device exists: on a CPU-only machine they are
    deselected (counted as such), not skipped. ../shared/gpu-checklist.md runs them on a GPU."""
    import torch

    if torch.cuda.is_available():
        return
    gpu = [item for item in items if item.get_closest_marker("gpu")]
    if gpu:
        config.hook.pytest_deselected(items=gpu)
        items[:] = [item for item in items if not item.get_closest_marker("gpu")]


def pytest_sessionfinish(session, exitstatus):
    """Under CI=true every declared extra, chromium and root are set up by scripts/setup.sh, so
    a skipped test means a broken setup: the run fails and says so (-rs lists the reasons)."""
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    skipped = reporter.stats.get("skipped", []) if reporter else []
    if os.environ.get("CI", "").lower() == "true" and skipped:
        reporter.write_sep("=", f"CI=true: {len(skipped)} skipped test(s) fail the run", red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """Keep a crash at interpreter exit diagnosable: pytest's own fault handler is switched off
    before this, so a native library that crashes while Python shuts down (its threads, its
    exit handlers) would end the run with a bare "Segmentation fault" and no stack."""
    faulthandler.enable(file=sys.__stderr__, all_threads=True)


@pytest.fixture
def make_dataset(tmp_path: Path):
    """Factory: make_dataset(presses=6, frames_per_press=40, image_size=64, ...) -> Path."""

    from helpers.synthetic_presses import write_synthetic_dataset

    def make(
        presses: int = 6,
        frames_per_press: int = 40,
        image_size: int = 64,
        seed: int = 0,
        name: str = "tiny.h5",
        fps: float = 30.0,
    ) -> Path:
        return write_synthetic_dataset(
            tmp_path / name, presses, frames_per_press, image_size, seed, fps
        )

    return make


def untrained_model(model: ModelConfig, seed: int) -> PressureModel:
    """An untrained model of this shape for 64x64 frames (output scale 10 kPa)."""
    import torch

    from beadsight.checkpoint import CheckpointMeta, PressureModel
    from beadsight.config import SensorGeometry

    torch.manual_seed(seed)
    meta = CheckpointMeta(
        model=model,
        geometry=SensorGeometry(image_size_px=64),
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=10.0,
    )
    return PressureModel.create(meta)


@pytest.fixture
def tiny_model() -> PressureModel:
    """An untrained width-8, 15-frame model for 64x64 frames."""
    from beadsight.config import ModelConfig

    return untrained_model(ModelConfig(frames=15, width=8), seed=0)


@pytest.fixture(scope="session")
def probe_model() -> PressureModel:
    """:func:`tiny_model`, shared by a session: inference tests must not change it."""
    from beadsight.config import ModelConfig

    return untrained_model(ModelConfig(frames=15, width=8), seed=0)


@pytest.fixture(scope="session")
def strided_model(probe_model) -> PressureModel:
    """probe_model's weights, seeing every 3rd frame of a 43-frame window."""
    from beadsight.checkpoint import PressureModel
    from beadsight.config import ModelConfig

    model = PressureModel.create(
        dataclasses.replace(probe_model.meta, model=ModelConfig(frames=15, frame_stride=3, width=8))
    )
    model.module.load_state_dict(probe_model.module.state_dict())
    return model


@pytest.fixture(scope="session")
def rest_model() -> PressureModel:
    """An untrained rest-referenced model for 64x64 frames: the rest image, then a span of
    7 frames of which it sees every 2nd (4 frames); shared by a session."""
    return make_rest_model()


@pytest.fixture(scope="session")
def rest_norm_model() -> PressureModel:
    """:func:`rest_model` with its rest input contrast-normalised (``rest_norm``)."""
    return make_rest_model(rest_norm=True)


def make_rest_model(rest_norm: bool = False) -> PressureModel:
    """:func:`rest_model`'s model, its rest input contrast-normalised with ``rest_norm``."""
    from beadsight.config import ModelConfig

    shape = ModelConfig(frames=4, frame_stride=2, width=8, rest_input=True, rest_norm=rest_norm)
    return untrained_model(shape, seed=1)


@pytest.fixture(scope="session")
def shared_cache(tmp_path_factory) -> Path:
    """A backend cache folder shared by every worker of this test run (not across runs), for
    tests whose subject is not quantizing or caching: the shipped model's int8 recipes and
    their gate verdicts are then made once per run, not once per test. Its writes are
    atomic (the int8 IR's weights before its graph), so workers that make the same file at
    once each read a whole one."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if "PYTEST_XDIST_WORKER" in os.environ else base
    folder = root / "shared-backend-cache"
    folder.mkdir(exist_ok=True)
    return folder


@pytest.fixture
def full_disk(tmp_path: Path):
    """A real small disk (tmpfs, 256 KiB) that fills up; skips where it cannot be mounted.

    Yields the mount point; writers tested on it must fail with a named error.
    """
    import subprocess

    mount = tmp_path / "small-disk"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


@pytest.fixture
def one_torch_thread():
    """The test machine is shared: one intra-op thread avoids spin-wait thrashing."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def rest_run(tmp_path_factory) -> tuple[Path, Path]:
    """A rest-referenced model trained 2 steps on a tiny dataset: (dataset, checkpoint).

    The dataset: 6 presses of 40 frames at 32 px (the first press has no rest image before
    it); the model: width 4, 3 frames, its split stored in the checkpoint."""
    import torch
    from helpers.synthetic_presses import write_synthetic_dataset

    from beadsight.train.config import TrainConfig
    from beadsight.train.trainer import train

    root = tmp_path_factory.mktemp("rest_run")
    data = write_synthetic_dataset(root / "rest.h5", image_size=32)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train(
            TrainConfig(
                data=str(data),
                out=str(root / "run"),
                rest_input=True,
                width=4,
                frames=3,
                steps=2,
                batch_size=8,
                device="cpu",
                loader="device",
                progress=False,
                checkpoint_every_min=1e6,
            )
        )
    finally:
        torch.set_num_threads(threads)
    return data, root / "run" / "best.pt"
