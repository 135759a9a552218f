"""The BeadSight U-Net, and the module that wraps it from uint8 frames to kPa.

``UNet`` is the reference network; its parameter names match the reference
state_dicts (``C1.layer.0.weight`` ... ``pred.bias``). ``FramesToPressure`` adds
the input handling (which frames of a window the network sees, the rest reference,
normalisation) and the output scale, so a single module maps ``(B, inputs, H, W, 3)``
uint8 RGB images to ``(B, H, W)`` kPa and exports as one graph. It is the only place
that input handling is written: every runtime and training step goes through its methods.

A *rest-referenced* model (``ModelConfig.rest_input``) reads pressure as the pouch's state
relative to its unloaded self: its input starts with one image of the pouch at rest
(the average of a few still, unloaded frames), followed by the window. The network sees
the rest image and each seen frame's difference from it, so a steady load stays visible
when the frames stop moving, and an unloaded pouch of any look reads as no change.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from beadsight.config import ModelConfig


class InstanceNorm(nn.InstanceNorm2d):
    """``nn.InstanceNorm2d`` without affine parameters or running statistics, computed as a
    group norm with one group per channel: the same statistics (mean and biased variance
    of each sample's channel, ``eps`` 1e-5), about twice as fast on CPUs in training and
    inference (``benchmarks/train_speed.py``). It has no state_dict entries, like
    ``nn.InstanceNorm2d``, and exports to ONNX as InstanceNormalization, as that does."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.onnx.is_in_onnx_export():
            return super().forward(x)
        return F.group_norm(x, self.num_features, eps=self.eps)


class ConvBlock(nn.Module):
    """conv3x3 -> InstanceNorm -> ELU -> Dropout, twice."""

    def __init__(self, c_in: int, c_out: int, dropout: float):
        super().__init__()
        self.layer = nn.Sequential(
            nn.Conv2d(c_in, c_out, 3, padding=1),  # layer.0
            InstanceNorm(c_out),
            nn.ELU(),
            nn.Dropout(dropout),
            nn.Conv2d(c_out, c_out, 3, padding=1),  # layer.4
            InstanceNorm(c_out),
            nn.ELU(),
            nn.Dropout(dropout),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layer(x)


class DownBlock(nn.Module):
    """Strided conv3x3 (C -> C) halving H and W, then LeakyReLU; no norm."""

    def __init__(self, c: int):
        super().__init__()
        self.Down = nn.Sequential(nn.Conv2d(c, c, 3, stride=2, padding=1), nn.LeakyReLU(0.01))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.Down(x)


class UpBlock(nn.Module):
    """Nearest x2 upsampling, conv (C -> C/2), then concatenate [up, skip].

    A 1x1 conv commutes with nearest upsampling (each output pixel is a copy of one input
    pixel, and the conv maps each pixel alone), so with ``kernel`` 1 the conv runs first,
    on a quarter of the pixels, and the upsampling copies half the channels. ONNX export
    keeps the reference order: the INT8 quantization of the other order moved the CoP
    error by +4 % on the metric gate's presses (``inference.int8``), the reference order
    by 0 %."""

    def __init__(self, c_in: int, kernel: int):
        super().__init__()
        self.Up = nn.Conv2d(c_in, c_in // 2, kernel, padding=kernel // 2)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        if self.Up.kernel_size == (1, 1) and not torch.onnx.is_in_onnx_export():
            up = F.interpolate(self.Up(x), scale_factor=2.0, mode="nearest")  # (B, C/2, 2H, 2W)
        else:
            up = self.Up(F.interpolate(x, scale_factor=2.0, mode="nearest"))  # (B, C/2, 2H, 2W)
        return torch.cat([up, skip], dim=1)  # (B, C, 2H, 2W)


class UNet(nn.Module):
    """Reference U-Net: (B, C, H, W) normalised frames -> (B, 1, H, W) >= 0, where
    C = 3T, or 3 (T + 1) for a rest-referenced model.

    H and W must be divisible by 8. The output is in units of the training
    target's scale (``FramesToPressure`` multiplies it back to kPa).
    """

    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        self.config = config
        w, p = config.width, config.dropout
        self.C1 = ConvBlock(3 * (config.frames + int(config.rest_input)), w, p)
        self.D1 = DownBlock(w)
        self.C2 = ConvBlock(w, 2 * w, p)
        self.D2 = DownBlock(2 * w)
        self.C3 = ConvBlock(2 * w, 4 * w, p)
        self.D3 = DownBlock(4 * w)
        self.C4 = ConvBlock(4 * w, 8 * w, p)
        self.U2 = UpBlock(8 * w, config.up_kernel)
        self.C7 = ConvBlock(8 * w, 4 * w, p)
        self.U3 = UpBlock(4 * w, config.up_kernel)
        self.C8 = ConvBlock(4 * w, 2 * w, p)
        self.U4 = UpBlock(2 * w, config.up_kernel)
        self.C9 = ConvBlock(2 * w, w, 0.0)
        self.pred = nn.Conv2d(w, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r1 = self.C1(x)  # (B, w, H, W)
        r2 = self.C2(self.D1(r1))  # (B, 2w, H/2, W/2)
        r3 = self.C3(self.D2(r2))  # (B, 4w, H/4, W/4)
        y = self.C4(self.D3(r3))  # (B, 8w, H/8, W/8)
        y = self.C7(self.U2(y, r3))  # (B, 4w, H/4, W/4)
        y = self.C8(self.U3(y, r2))  # (B, 2w, H/2, W/2)
        y = self.C9(self.U4(y, r1))  # (B, w, H, W)
        return F.relu(self.pred(y))  # (B, 1, H, W)


def infer_model_config(
    state_dict: dict[str, torch.Tensor], dropout: float = 0.2, rest_input: bool = False
) -> ModelConfig:
    """Read frames (T), width and up-conv kernel from a U-Net state_dict's tensor shapes.

    The frame stride and the rest input are not in the weights: this gives stride 1, and
    takes ``rest_input`` as given (False for reference checkpoints)."""
    try:
        first = state_dict["C1.layer.0.weight"]  # (w, 3T, 3, 3)
        up = state_dict["U2.Up.weight"]  # (4w, 8w, k, k)
    except KeyError as e:
        raise ValueError(f"not a BeadSight U-Net state_dict: missing {e.args[0]!r}") from None
    if first.shape[1] % 3:
        raise ValueError(f"C1.layer.0.weight has {first.shape[1]} input channels; expected 3*T")
    frames = first.shape[1] // 3 - int(rest_input)
    if frames < 1:
        raise ValueError(f"C1.layer.0.weight has {first.shape[1]} input channels; too few for rest")
    return ModelConfig(
        frames=frames,
        width=first.shape[0],
        up_kernel=up.shape[-1],
        dropout=dropout,
        rest_input=rest_input,
    )


class FramesToPressure(nn.Module):
    """uint8 RGB frame windows -> kPa maps, with the input handling inside the module.

    images: (B, inputs, H, W, 3) uint8 RGB: for a rest-referenced model the rest image
    first, then the window's ``span`` frames, oldest first (``inputs = span + rest``).
    The network sees ``config.frames`` of the window, every ``frame_stride``-th counted
    back from the newest (:meth:`seen`).
    returns: (B, H, W) float32 kPa.

    ``channel_order`` is the order the network was trained on ("RGB" or "BGR");
    ``pixel_mean``/``pixel_std`` are per-channel statistics in that order, in
    0..255 units; ``output_scale_kpa`` converts the network's output to kPa.

    The steps, for runtimes that keep normalised frames between calls::

        x = module.normalize_frames(frames)  # each frame once: (B, N, 3, H, W)
        y = module.pressure(module.stack(x))  # one input of ``inputs`` images -> (B, H, W) kPa
    """

    def __init__(
        self,
        net: UNet,
        pixel_mean: list[float] | tuple[float, ...],
        pixel_std: list[float] | tuple[float, ...],
        channel_order: str = "RGB",
        output_scale_kpa: float = 1.0,
    ):
        super().__init__()
        if channel_order not in ("RGB", "BGR"):
            raise ValueError(f"channel_order must be 'RGB' or 'BGR', got {channel_order!r}")
        self.net = net
        self.channel_order = channel_order
        perm = [2, 1, 0] if channel_order == "BGR" else [0, 1, 2]
        self.register_buffer("channel_perm", torch.tensor(perm), persistent=False)
        self.register_buffer("pixel_mean", torch.tensor(pixel_mean, dtype=torch.float32))
        self.register_buffer("pixel_std", torch.tensor(pixel_std, dtype=torch.float32))
        self.register_buffer("output_scale_kpa", torch.tensor(float(output_scale_kpa)))

    @property
    def frames(self) -> int:
        """T: frames the network sees."""
        return self.net.config.frames

    @property
    def span(self) -> int:
        """Consecutive frames one input window covers (oldest first)."""
        return self.net.config.span

    @property
    def rest(self) -> int:
        """1 if the input starts with a rest image (rest-referenced model), else 0."""
        return int(self.net.config.rest_input)

    @property
    def inputs(self) -> int:
        """Images in one input: ``rest`` + ``span``."""
        return self.net.config.inputs

    def seen(self, window: torch.Tensor) -> torch.Tensor:
        """(B, span, ...) -> (B, T, ...): the frames the network sees, the newest included."""
        stride = self.net.config.frame_stride
        return window[:, ::stride] if stride > 1 else window

    def normalize_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """(B, N, H, W, 3) uint8 RGB -> (B, N, 3, H, W) float32, channels in the trained
        order, ``(x - pixel_mean) / pixel_std``."""
        x = frames.index_select(-1, self.channel_perm).to(torch.float32)
        x = (x - self.pixel_mean) / self.pixel_std  # (B, N, H, W, 3)
        return x.permute(0, 1, 4, 2, 3)

    def stack(self, normalized: torch.Tensor) -> torch.Tensor:
        """(B, inputs, 3, H, W) normalised images -> (B, C, H, W) network input.

        Without rest: channel k = 3t + c over the T frames the network sees (C = 3T).
        With rest: the rest image's 3 channels, then each seen frame minus the rest
        image (C = 3 + 3T)."""
        if not self.rest:
            return self.stack_window(normalized)
        return self.stack_window(normalized[:, 1:], normalized[:, :1])

    def stack_window(self, window: torch.Tensor, rest: torch.Tensor | None = None) -> torch.Tensor:
        """:meth:`stack` with the rest image apart: window (B, span, 3, H, W) and, for a
        rest-referenced model, rest (B, 1, 3, H, W), normalised -> (B, C, H, W)."""
        if rest is None:
            return self.seen(window).flatten(1, 2)  # (B, 3T, H, W)
        return self._relative(rest, self.seen(window))

    def normalize(self, images: torch.Tensor) -> torch.Tensor:
        """(B, inputs, H, W, 3) uint8 RGB -> (B, C, H, W) float32 network input
        (only the images the network sees are normalised)."""
        if not self.rest:
            return self.normalize_frames(self.seen(images)).flatten(1, 2)  # only the T seen
        rest = self.normalize_frames(images[:, :1])  # (B, 1, 3, H, W)
        return self._relative(rest, self.normalize_frames(self.seen(images[:, 1:])))

    def _relative(self, rest: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """rest (B, 1, 3, H, W), seen (B, T, 3, H, W) normalised -> (B, 3 + 3T, H, W):
        the rest image, then each seen frame's change from it (:meth:`rest_terms`)."""
        return torch.cat(self.rest_terms(rest, seen), dim=1).flatten(1, 2)

    def rest_terms(
        self, rest: torch.Tensor, frames: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """rest (B, 1, 3, H, W), frames (B, N, 3, H, W) normalised -> the rest image's
        planes of the network input (B, 1, 3, H, W) and each frame's (B, N, 3, H, W): its
        change from the rest image. Each frame's term depends on that frame and the rest
        image alone, so a streaming runtime can compute it once per frame.

        With ``rest_norm`` both are in units of the rest image's own per-channel contrast
        (its spatial standard deviation), and the rest image is centred on its mean: the
        input no longer changes when a pouch's colours are scaled or shifted, rest and
        window alike (another LED, exposure or bead tint)."""
        change = frames - rest
        if self.net.config.rest_norm:
            mean = rest.mean(dim=(-2, -1), keepdim=True)  # (B, 1, 3, 1, 1)
            scale = (rest - mean).square().mean(dim=(-2, -1), keepdim=True).add(1e-4).rsqrt()
            rest, change = (rest - mean) * scale, change * scale
        return rest, change

    def pressure(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3T, H, W) network input -> (B, H, W) kPa."""
        return self.net(x)[:, 0] * self.output_scale_kpa

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return self.pressure(self.normalize(frames))  # (B, H, W)
