"""Quantization-aware training (``beadsight train --qat``): weights that keep the
paper's metrics under the int8 runtime.

Post-training int8 (:mod:`beadsight.inference.int8`) moved the reference-size model's
MAE by +2.03 % relative to fp32 on the metric gate's presses, over its 2 % bound. With
``--qat`` the U-Net trains through NNCF's fake quantizers at every convolution but the
output's (:data:`QUANTIZED`: the int8 runtime's own quantizers and those of the
full-resolution blocks it keeps in fp32), ranged on the runtime's calibration windows.
Validation, and so ``best.pt``, runs through them too.

Checkpoints keep plain fp32 weights, so every runtime reads them as before; the int8
runtime quantizes them with its own recipe and the metric gate judges the result as it
judges any model. ``last.pt`` also keeps the quantizers' learnt ranges, so ``--resume``
goes on with them. Measured in docs/live.md ("Quantization-aware training"; its fp32
control: the same steps without ``--qat`` brought the default recipe within the gate
too, so most of that gain was the further training).
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

import torch

from beadsight.checkpoint import PressureModel
from beadsight.errors import ConfigError
from beadsight.inference.int8 import QuantizationRecipe, calibration_windows
from beadsight.inference.machine import import_openvino
from beadsight.train.step import model_inputs

QUANTIZED = QuantizationRecipe(fp32_blocks=("pred",))  # what training quantizes
QUANTIZERS = "__nncf_hooks."  # state-dict keys of NNCF's quantizers (the rest: the U-Net's)


def quantization_aware(model: PressureModel) -> torch.nn.Module:
    """A copy of ``model``'s U-Net with NNCF fake quantizers as :data:`QUANTIZED` puts
    them, ranged on the int8 runtime's calibration windows (simulated presses at the
    model's size) through ``model``'s normalisation."""
    try:
        import_openvino()  # first: nncf must not load its telemetry
        import nncf
    except ImportError:
        raise ConfigError("--qat needs nncf; `pip install beadsight[openvino]`") from None
    module = model.module
    device = next(module.parameters()).device
    with torch.no_grad():
        inputs = [
            model_inputs(module, torch.from_numpy(w[None]).to(device))
            for w in calibration_windows(model)
        ]
    nncf_log = logging.getLogger("nncf")  # INFO lines and progress bars on stdout
    level = nncf_log.level
    nncf_log.setLevel(logging.WARNING)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            return nncf.quantize(
                module.net,
                nncf.Dataset(inputs),
                subset_size=len(inputs),
                **QUANTIZED.nncf_options(nncf, graph="torch"),
            )
    finally:
        nncf_log.setLevel(level)


def plain_weights(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The U-Net's own weights of a :func:`quantization_aware` copy."""
    return {k: v for k, v in net.state_dict().items() if not k.startswith(QUANTIZERS)}


def quantizer_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The quantizers' state (learnt ranges) of a :func:`quantization_aware` copy."""
    return {k: v.detach().cpu() for k, v in net.state_dict().items() if k.startswith(QUANTIZERS)}


class QuantizationAware:
    """A ``--qat`` run's two U-Nets: ``module.net`` becomes the :func:`quantization_aware`
    copy that trains, and the plain one is kept to save the trained weights into."""

    def __init__(self, model: PressureModel):
        self.module, self.plain = model.module, model.module.net
        net = quantization_aware(model).to(next(self.plain.parameters()).device).train()
        self.module.net = net

    def restore(self, ranges: dict[str, torch.Tensor]) -> None:
        """Put back the quantizers' state that :meth:`saving` gave (a resumed run)."""
        net = self.module.net
        net.load_state_dict({**plain_weights(net), **ranges})

    @contextlib.contextmanager
    def saving(self) -> Iterator[dict[str, dict[str, torch.Tensor]]]:
        """Within: ``module.net`` is the plain U-Net holding the trained weights; yields
        the training state to save beside them (the quantizers' ranges)."""
        net = self.module.net
        self.plain.load_state_dict(plain_weights(net))
        self.module.net = self.plain
        try:
            yield {"qat_quantizers": quantizer_state(net)}
        finally:
            self.module.net = net
