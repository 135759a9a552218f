"""One device rule for training, evaluation, prediction and the demo.

MPS cannot run here, so its availability is switched on with monkeypatch where the rule
for an available MPS is checked; everything else runs on this machine's real torch.
"""

from __future__ import annotations

import pytest
import torch

from beadsight.torch_device import DeviceError, mps_available, resolve_device

HAS_CUDA = torch.cuda.is_available()


@pytest.fixture
def fake_mps(monkeypatch):
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)


def test_auto_is_cuda_else_cpu():
    assert resolve_device("auto") == torch.device("cuda" if HAS_CUDA else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")


def test_auto_never_picks_mps(fake_mps):
    assert mps_available()
    assert resolve_device("auto").type == ("cuda" if HAS_CUDA else "cpu")


def test_mps_by_name_when_available(fake_mps):
    assert resolve_device("mps") == torch.device("mps")


@pytest.mark.skipif(mps_available(), reason="this machine has MPS")
def test_mps_by_name_when_unavailable_is_refused():
    with pytest.raises(DeviceError, match="--device 'mps': MPS is not available"):
        resolve_device("mps", "--device")


@pytest.mark.skipif(HAS_CUDA, reason="this machine has CUDA")
def test_cuda_without_a_gpu_is_refused():
    for name in ("cuda", "cuda:1"):
        with pytest.raises(DeviceError, match=f"device '{name}': CUDA is not available"):
            resolve_device(name)


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
def test_cuda_index_beyond_the_gpus_is_refused():
    count = torch.cuda.device_count()
    assert resolve_device("cuda:0") == torch.device("cuda:0")
    with pytest.raises(DeviceError, match=f"has {count} CUDA device"):
        resolve_device(f"cuda:{count}")


def test_unknown_devices_are_refused():
    with pytest.raises(DeviceError, match="'gpu': not a torch device.*auto, cpu, cuda"):
        resolve_device("gpu")
    with pytest.raises(DeviceError, match="'meta': unsupported device type"):
        resolve_device("meta")


def test_training_follows_the_rule(fake_mps, monkeypatch, tmp_path):
    """Training accepts mps by name (one process), like prediction; auto stays off it."""
    from beadsight.config import ConfigError
    from beadsight.train.config import TrainConfig
    from beadsight.train.distributed import resolve_device as train_device

    def config(**kw):
        return TrainConfig(data=str(tmp_path / "d.h5"), out=str(tmp_path / "run"), **kw)

    assert train_device("mps") == torch.device("mps")
    assert train_device("auto").type == ("cuda" if HAS_CUDA else "cpu")
    with pytest.raises(ConfigError, match="precision fp16 needs a CUDA device.*on mps"):
        train_device("mps", "fp16")
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ConfigError, match="device mps: one process only"):
        train_device("mps")
    with pytest.raises(ConfigError, match="device must be auto, cpu, cuda, cuda:N or mps"):
        config(device="tpu")


@pytest.mark.skipif(mps_available(), reason="this machine has MPS")
def test_prediction_and_training_refuse_the_same_unavailable_device(tiny_model, tmp_path):
    from beadsight.evaluation.predict import as_model
    from beadsight.train.config import TrainConfig
    from beadsight.train.distributed import resolve_device as train_device

    with pytest.raises(DeviceError, match="MPS is not available"):
        as_model(tiny_model, "mps")
    config = TrainConfig(data=str(tmp_path / "d.h5"), out=str(tmp_path / "run"), device="mps")
    with pytest.raises(DeviceError, match="MPS is not available"):
        train_device(config.device, config.precision)
