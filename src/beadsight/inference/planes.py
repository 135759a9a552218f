"""The network's own input, kept per frame: what the ONNX and OpenVINO runtimes run.

An exported model (:mod:`beadsight.inference.export_format`) takes uint8 windows and
normalises every frame of the window inside the graph, on every call. A runtime that
streams need not: each frame's planes of the network input (the normalised frame, or its
change from the rest image: :meth:`~beadsight.model.FramesToPressure.rest_terms`)
depend on that frame and the rest image alone. So the file runtimes built from a
checkpoint run the network alone (:func:`ring_network`) on float32 planes, and a
:class:`PlaneRing` computes each frame's planes once, when it arrives, into a ring laid
out as the network reads it: the window is a contiguous view, handed to the runtime
without a copy. :func:`ring_inputs` gives the same planes for whole windows (the
stateless calls: evaluation, parity checks, int8 calibration).

Ring order. The network's input is the rest image's planes, then the seen frames',
oldest first. The ring keeps the seen frames' planes contiguous, doubled (slots ``i`` and
``i + T``), and writes the rest planes in the slot after the newest frame's (one that no
later view reads), so the graph takes the rest planes last: its first convolution's
input channels are permuted to match, which is exact (a convolution sums over its input
channels). A model with a frame stride keeps one ring per phase of the stride.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch
from torch import nn

from beadsight.files import atomic_write_bytes
from beadsight.inference.export_format import onnx_bytes
from beadsight.model import FramesToPressure

GRAPH_VERSION = "ring-planes-v1"  # names cached graphs; change when the graph changes


class RingOrderNetwork(nn.Module):
    """The U-Net of a :class:`FramesToPressure` module on its input planes in ring order
    (the seen frames' planes, then a rest-referenced model's rest planes) -> (B, H, W)
    kPa. Node names are those of the whole module's export (``/net/C1/...``), so int8
    recipes address the same blocks."""

    def __init__(self, module: FramesToPressure):
        super().__init__()
        self.net = copy.deepcopy(module.net).cpu().eval()
        if module.rest:  # the rest image's 3 channels move from first to last
            conv = self.net.C1.layer[0]
            order = [*range(3, conv.in_channels), 0, 1, 2]
            with torch.no_grad():
                conv.weight.copy_(conv.weight[:, order])
        self.register_buffer("output_scale_kpa", module.output_scale_kpa.detach().cpu().clone())

    def forward(self, planes: torch.Tensor) -> torch.Tensor:
        return self.net(planes)[:, 0] * self.output_scale_kpa


def ring_network(module: FramesToPressure) -> RingOrderNetwork:
    return RingOrderNetwork(module).eval()


def write_network_onnx(module: FramesToPressure, image_size: int, path: str | Path) -> Path:
    """Export :func:`ring_network` to ONNX (input ``planes`` (B, C, S, S) float32, a
    dynamic batch axis), atomically. The runtimes' internal graph: no metadata."""
    channels = module.net.C1.layer[0].in_channels
    example = torch.zeros((1, channels, image_size, image_size), dtype=torch.float32)
    return atomic_write_bytes(path, onnx_bytes(ring_network(module), example, "planes"))


@torch.inference_mode()
def ring_inputs(module: FramesToPressure, images: np.ndarray) -> np.ndarray:
    """(B, inputs, S, S, 3) uint8 RGB images (as ``Backend.run`` takes them) -> (B, C, S,
    S) float32 network input in ring order."""
    x = module.normalize(torch.from_numpy(np.ascontiguousarray(images)))
    if module.rest:
        x = torch.cat([x[:, 3:], x[:, :3]], dim=1)
    return x.contiguous().numpy()


class PlaneRing:
    """Each frame's network-input planes, computed once, in ring order.

    :meth:`update` takes what ``Backend.run_incremental`` takes (the window, how many of
    its last frames are new, the rest image) and returns the network input (1, C, S, S)
    float32: a view into the ring, valid until the next call.
    """

    def __init__(self, module: FramesToPressure, image_size: int):
        self.module = module
        config = module.net.config
        self.frames, self.stride, self.span = config.frames, config.frame_stride, config.span
        seen = module.seen(torch.arange(self.span)[None])[0].tolist()
        if seen != list(range(0, self.span, self.stride)):  # what the layout below assumes
            raise ValueError(f"the ring needs every {self.stride}-th frame, oldest first")
        self.rest = module.rest
        t, s = self.frames, image_size
        # per phase of the stride: slots 0..2T-1 the doubled ring, slot 2T the rest planes'
        self._slots = np.zeros((self.stride, 2 * t + self.rest, 3, s, s), dtype=np.float32)
        self._heads = [-1] * self.stride  # per phase: the slot of its newest frame
        self._pushed = 0  # frames pushed since the last load; the newest's phase: (n-1) % stride
        self._rest_image: np.ndarray | None = None  # the rest image the planes are relative to
        self._rest_x: torch.Tensor | None = None  # ... normalised (1, 1, 3, S, S)
        self._rest_planes: np.ndarray | None = None  # ... its own planes (3, S, S)

    @property
    def channels(self) -> int:
        return 3 * (self.frames + self.rest)

    def update(
        self, window: np.ndarray, new_frames: int, rest: np.ndarray | None = None
    ) -> np.ndarray:
        """window (1, span, S, S, 3) uint8, the last ``new_frames`` of them new since the
        previous call (``>= span``: all new); rest (S, S, 3) uint8 for a rest-referenced
        model. A new rest image recomputes every frame's planes from the window."""
        if self.rest and self._set_rest(rest):
            new_frames = self.span
        if self._pushed == 0 or new_frames >= self.span:
            self._heads, self._pushed = [-1] * self.stride, 0
            self._push(window[0])
        elif new_frames > 0:
            self._push(window[0, self.span - int(new_frames) :])
        phase = (self._pushed - 1) % self.stride
        head, t = self._heads[phase], self.frames
        slots = self._slots[phase]
        if self.rest:  # the slot after the newest: the oldest frame's upper copy, or 2T
            slots[head + 1 + t] = self._rest_planes
        return slots[head + 1 : head + 1 + t + self.rest].reshape(
            1, self.channels, *slots.shape[2:]
        )

    def _set_rest(self, rest: np.ndarray | None) -> bool:
        """Take the rest image; True when it differs from the one the ring holds."""
        if rest is self._rest_image or (
            self._rest_image is not None and np.array_equal(rest, self._rest_image)
        ):
            self._rest_image = rest
            return False
        with torch.inference_mode():
            x = self.module.normalize_frames(
                torch.from_numpy(np.array(rest, order="C"))[None, None]
            )
            planes, _ = self.module.rest_terms(x, x[:, :0])
        self._rest_image, self._rest_x, self._rest_planes = rest, x, planes[0, 0].numpy()
        return True

    @torch.inference_mode()
    def _push(self, frames: np.ndarray) -> None:
        """Compute the planes of (N, S, S, 3) uint8 frames, oldest first, into the ring."""
        x = self.module.normalize_frames(torch.from_numpy(np.ascontiguousarray(frames))[None])
        if self.rest:
            _, x = self.module.rest_terms(self._rest_x, x)
        t = self.frames
        for planes in x[0].numpy():
            phase = self._pushed % self.stride
            head = (self._heads[phase] + 1) % t
            self._slots[phase, head] = planes
            self._slots[phase, head + t] = planes
            self._heads[phase], self._pushed = head, self._pushed + 1
