"""The U-Net's faster pieces compute what the plain ones do (issue 24, training speed):
its InstanceNorm (a group norm of one channel per group) against ``nn.InstanceNorm2d``,
and the 1x1 up-conv before the upsampling against the conv after it."""

from __future__ import annotations

import io
from collections import Counter

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from beadsight.config import ModelConfig
from beadsight.model import FramesToPressure, InstanceNorm, UNet, UpBlock


def plain_unet(config: ModelConfig) -> UNet:
    """A UNet whose norms are nn.InstanceNorm2d and whose up blocks upsample first."""
    net = UNet(config)

    def upsample_first(self, x, skip):
        return torch.cat([self.Up(F.interpolate(x, scale_factor=2.0, mode="nearest")), skip], 1)

    for block in net.modules():
        if isinstance(block, UpBlock):
            block.forward = upsample_first.__get__(block)
        if hasattr(block, "layer"):
            for i in (1, 5):
                block.layer[i] = nn.InstanceNorm2d(block.layer[i].num_features)
    return net


@pytest.mark.parametrize("shape", [(2, 8, 16, 16), (3, 5, 7, 9), (1, 32, 1, 4)])
def test_instance_norm_matches_torch_instance_norm(shape):
    x = torch.randn(shape, dtype=torch.float64) * 3 + 1.5
    x.requires_grad_(True)
    y = InstanceNorm(shape[1])(x)
    x2 = x.detach().clone().requires_grad_(True)
    y2 = nn.InstanceNorm2d(shape[1])(x2)
    torch.testing.assert_close(y, y2)
    w = torch.randn(shape, dtype=torch.float64)
    (y * w).sum().backward()
    (y2 * w).sum().backward()
    torch.testing.assert_close(x.grad, x2.grad)
    assert InstanceNorm(shape[1]).state_dict() == {}  # no weights: old checkpoints load


@pytest.mark.parametrize("up_kernel", [1, 3])
@pytest.mark.parametrize("mode", ["train", "eval"])
def test_unet_matches_the_plain_unet(up_kernel, mode):
    config = ModelConfig(
        frames=4, frame_stride=2, width=8, up_kernel=up_kernel, dropout=0.0, rest_input=True
    )
    torch.manual_seed(0)
    net = UNet(config)
    plain = plain_unet(config)
    assert list(plain.state_dict()) == list(net.state_dict())  # the same checkpoint keys
    plain.load_state_dict(net.state_dict())
    getattr(net, mode)()
    getattr(plain, mode)()
    x = torch.randn(3, 15, 32, 32)
    out, expected = net(x), plain(x)
    assert expected.abs().max() > 0.1
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)
    if mode == "train":  # one optimizer step's gradients agree too
        out.square().mean().backward()
        expected.square().mean().backward()
        for (name, p), q in zip(net.named_parameters(), plain.parameters(), strict=True):
            torch.testing.assert_close(p.grad, q.grad, rtol=1e-3, atol=1e-6, msg=name)


def test_onnx_export_keeps_instance_normalization():
    pytest.importorskip("onnx")
    import onnx

    net = UNet(ModelConfig(frames=1, width=4, dropout=0.0)).eval()
    buffer = io.BytesIO()
    with torch.no_grad():
        torch.onnx.export(net, (torch.zeros(1, 3, 16, 16),), buffer, dynamo=False, opset_version=17)
    ops = Counter(node.op_type for node in onnx.load_from_string(buffer.getvalue()).graph.node)
    norms = sum(isinstance(m, InstanceNorm) for m in net.modules())
    assert norms == 14 and ops["InstanceNormalization"] == norms
    # a group norm would export as Reshape -> InstanceNormalization -> Reshape -> Mul -> Add
    assert ops["Reshape"] == ops["Mul"] == ops["Add"] == ops["GroupNormalization"] == 0


def test_rest_norm_input_ignores_a_pouchs_colour_gain_and_offset():
    """With ``rest_norm`` the network input is the same when rest and window alike have
    each colour channel scaled and shifted (another LED, exposure or bead tint); without
    it, it is not. Invalid without a rest input."""
    torch.manual_seed(0)
    images = torch.randint(20, 200, (2, 8, 16, 16, 3)).float()  # rest + span 7
    gain, offset = torch.tensor([0.6, 1.3, 0.9]), torch.tensor([25.0, -10.0, 5.0])
    for norm in (True, False):
        config = ModelConfig(frames=4, frame_stride=2, width=4, rest_input=True, rest_norm=norm)
        module = FramesToPressure(UNet(config), [120.0] * 3, [40.0] * 3)
        x, y = module.normalize(images), module.normalize(images * gain + offset)
        assert x.shape == (2, 15, 16, 16)
        assert torch.allclose(x, y, rtol=1e-3, atol=1e-3) == norm
    with pytest.raises(ValueError, match="rest_norm needs rest_input"):
        ModelConfig(rest_norm=True)
