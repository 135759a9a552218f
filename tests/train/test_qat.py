"""Quantization-aware training (``beadsight train --qat``).

The U-Net trains through int8 fake quantizers at every convolution but the output's;
checkpoints keep plain fp32 weights that every runtime reads and say how they were
trained; ``--resume`` goes on with the quantizers' learnt ranges.

NNCF's fake quantization runs here on NNCF's own pure-torch functions, the ones NNCF
itself falls back to where it cannot build its CPU kernels: building them takes about
25 s on a fresh machine, and what is tested is the training around them.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest
import torch
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight import load_checkpoint
from beadsight.checkpoint import CheckpointError, read_checkpoint_file
from beadsight.train.config import TrainConfig
from beadsight.train.distributed import Distributed
from beadsight.train.qat import QUANTIZERS, plain_weights, quantizer_state
from beadsight.train.step import model_inputs
from beadsight.train.trainer import Trainer


@pytest.fixture(autouse=True)
def nncf_reference_functions(monkeypatch):
    """NNCF's pure-torch quantize functions (its fallback, without its torch.compile)."""
    from nncf.torch.quantization.extensions import QuantizedFunctionsCPU
    from nncf.torch.quantization.reference import torch_executor

    functions = SimpleNamespace(
        Quantize_forward=torch_executor.forward, Quantize_backward=torch_executor.backward
    )
    monkeypatch.setattr(QuantizedFunctionsCPU, "_loaded_namespace", functions)


def _trainer(config: TrainConfig) -> Trainer:
    trainer = Trainer(config, Distributed(), torch.device("cpu"))
    trainer.setup()
    return trainer


def test_qat_trains_through_the_int8_quantizers_and_saves_plain_weights(make_dataset, tmp_path):
    run = tmp_path / "run"
    config = TrainConfig(
        data=str(make_dataset()),
        out=str(run),
        qat=True,
        steps=3,
        batch_size=4,
        width=8,
        frames=2,
        rest_input=True,
        dropout=0.0,
        noise_std=0.0,
        progress=False,
    )
    trainer = _trainer(config)
    net, plain = trainer.module.net, trainer.qat.plain
    assert quantizer_state(net) and not quantizer_state(plain)
    quantized = {k.split(".")[2].split("/")[0] for k in quantizer_state(net)}  # C1/layer/...
    assert {"C1", "C9", "D1", "U4"} <= quantized and "pred" not in quantized
    trainer.train_loader.set_epoch(0)
    frames, _ = next(iter(trainer.train_loader))
    with torch.no_grad():
        x = model_inputs(trainer.module, frames)
        quantized, exact = net.eval()(x), plain.eval()(x)
    net.train()
    # the trained net is the plain one seen through int8: close to it, not equal
    assert not torch.equal(quantized, exact)
    assert (quantized - exact).abs().max() < 0.2 * exact.abs().max()
    before = {k: v.clone() for k, v in plain_weights(net).items()}
    trainer.loop()
    trainer.close()
    trained = plain_weights(net)
    assert any(not torch.equal(before[k], trained[k]) for k in before)

    for name in ("last.pt", "best.pt"):
        model = load_checkpoint(run / name)  # a plain checkpoint: every runtime reads it
        assert model.meta.training["config"]["qat"] is True
    saved = load_checkpoint(run / "last.pt").module.net.state_dict()
    assert set(saved) == set(trained) and all(torch.equal(saved[k], trained[k]) for k in saved)
    ranges = read_checkpoint_file(run / "last.pt")["qat_quantizers"]
    assert ranges and all(k.startswith(QUANTIZERS) for k in ranges)

    resumed = _trainer(dataclasses.replace(config, resume=True, steps=4))
    state = resumed.module.net.state_dict()
    assert all(torch.equal(state[k], v) for k, v in ranges.items())  # the learnt ranges
    resumed.loop()
    resumed.close()
    state = read_checkpoint_file(run / "last.pt")
    assert state["step"] == 4

    del state["qat_quantizers"]  # a last.pt that lost them cannot go on as the same run
    torch.save(state, run / "last.pt")
    with pytest.raises(CheckpointError, match="last.pt.*cannot be resumed"):
        _trainer(dataclasses.replace(config, resume=True, steps=5))
