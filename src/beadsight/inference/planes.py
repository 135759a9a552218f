"""The network's own input, kept per frame: what the ONNX and OpenVINO runtimes run.

An exported model (:mod:`beadsight.inference.export_format`) takes uint8 windows and
normalises every frame of the window inside the graph, on every call. A runtime that
streams need not: each frame's planes of the network input (the normalised frame, or its
change from the rest image: :meth:`~beadsight.model.FramesToPressure.rest_terms`)
depend on that frame and the rest image alone. So the file runtimes built from a
checkpoint run the network alone (:class:`RingOrderNetwork`) on float32 planes, and a
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

A graph whose first step quantizes its input (an int8 recipe with the first convolution in
int8) takes the planes already quantized, uint8 (:class:`PlaneQuantizer`): the ring then
quantizes each frame's planes once, when it arrives, instead of the graph quantizing the
whole window on every call, and hands the runtime a quarter of the bytes.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from beadsight.files import atomic_write_bytes
from beadsight.inference.export_format import onnx_bytes
from beadsight.model import FramesToPressure

GRAPH_VERSION = "ring-planes-v2"  # names cached graphs; change when the graph changes


@dataclass(frozen=True)
class PlaneQuantizer:
    """The uint8 planes a graph takes when its first step quantizes its input: a plane
    value ``x`` is ``q = round(x / scale) + zero_point`` clipped to 0..255, and the graph
    reads ``(q - zero_point) * scale`` (the quantizer it replaces: 256 levels, per tensor)."""

    zero_point: int
    scale: float

    def __call__(self, planes: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 planes -> uint8 (into ``out`` when given)."""
        q = np.divide(planes, np.float32(self.scale), dtype=np.float32)
        q += np.float32(self.zero_point)
        np.clip(q, 0, 255, out=q)
        np.rint(q, out=q)
        if out is None:
            return q.astype(np.uint8)
        np.copyto(out, q, casting="unsafe")
        return out


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


def write_network_onnx(module: FramesToPressure, image_size: int, path: str | Path) -> Path:
    """Export :class:`RingOrderNetwork` to ONNX (input ``planes`` (B, C, S, S) float32, a
    dynamic batch axis), atomically. The runtimes' internal graph: no metadata."""
    channels = module.net.C1.layer[0].in_channels
    example = torch.zeros((1, channels, image_size, image_size), dtype=torch.float32)
    return atomic_write_bytes(path, onnx_bytes(RingOrderNetwork(module), example, "planes"))


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
    float32 (uint8 with a ``quantizer``): a view into the ring, valid until the next call.

    A frame's planes are affine in its pixel values, per colour channel (normalisation,
    the rest image's change, ``rest_norm``'s contrast scale), so the ring reads that map
    off the module once per rest image (:meth:`_derive`: the module's own steps on a
    black frame and one frame per colour, checked on the rest image) and applies it with
    numpy, one pass per plane, so no torch threads are woken between two runs of the
    runtime's own (with the torch steps per frame, streaming int8 at the reference size
    gained 1.04x over the whole-module graph instead of 1.18x: docs/live.md).
    """

    def __init__(
        self, module: FramesToPressure, image_size: int, quantizer: PlaneQuantizer | None = None
    ):
        self.module, self.quantizer = module, quantizer
        config = module.net.config
        self.frames, self.stride, self.span = config.frames, config.frame_stride, config.span
        seen = module.seen(torch.arange(self.span)[None])[0].tolist()
        if seen != list(range(0, self.span, self.stride)):  # what the layout below assumes
            raise ValueError(f"the ring needs every {self.stride}-th frame, oldest first")
        self.rest, self.image_size = module.rest, image_size
        t, s = self.frames, image_size
        # per phase of the stride: slots 0..2T-1 the doubled ring, slot 2T the rest planes'
        dtype = np.float32 if quantizer is None else np.uint8
        self._slots = np.zeros((self.stride, 2 * t + self.rest, 3, s, s), dtype=dtype)
        self._planes = np.empty((3, s, s), np.float32)  # one frame's, before quantizing
        self._heads = [-1] * self.stride  # per phase: the slot of its newest frame
        self._pushed = 0  # frames pushed since the last load; the newest's phase: (n-1) % stride
        self._rest_image: np.ndarray | None = None  # the rest image the planes are relative to
        self._rest_planes: np.ndarray | None = None  # ... its own planes (3, S, S)
        self._gain: np.ndarray | None = None  # (3 in, 3 out): planes = gain-weighted frame ...
        self._offset: np.ndarray | None = None  # ... + offset (3, S, S)
        if not self.rest:
            self._derive(None)

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
            new_frames = self.span
        for frame in window[0, self.span - min(int(new_frames), self.span) :]:
            self._push(frame)
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
        self._derive(np.array(rest, order="C"))
        self._rest_image = rest
        return True

    @torch.inference_mode()
    def _terms(self, frames: np.ndarray, rest_x: torch.Tensor | None) -> torch.Tensor:
        """The module's own planes of (N, S, S, 3) uint8 frames: (N, 3, S, S)."""
        x = self.module.normalize_frames(torch.from_numpy(frames)[None])
        return (x if rest_x is None else self.module.rest_terms(rest_x, x)[1])[0]

    @torch.inference_mode()
    def _derive(self, rest: np.ndarray | None) -> None:
        """Read the per-channel affine map of a frame's planes off the module (relative to
        ``rest`` for a rest-referenced model), and the rest image's own planes."""
        s = self.image_size
        rest_x = None
        if rest is not None:
            rest_x = self.module.normalize_frames(torch.from_numpy(rest)[None, None])
            planes, _ = self.module.rest_terms(rest_x, rest_x[:, :0])
            self._rest_planes = planes[0, 0].numpy()
            if self.quantizer is not None:
                self._rest_planes = self.quantizer(self._rest_planes)
        probes = np.zeros((4, s, s, 3), dtype=np.uint8)  # black, then each colour at 255
        for k in range(3):
            probes[k + 1, ..., k] = 255
        terms = self._terms(probes, rest_x).numpy()
        self._offset = terms[0]
        change = (terms[1:] - terms[:1]).mean(axis=(-2, -1), dtype=np.float64) / 255
        self._gain = change.astype(np.float32)  # (3 in, 3 out)
        self._gain[np.abs(self._gain) < 1e-12] = 0.0
        check = rest if rest is not None else np.full((s, s, 3), 128, np.uint8)
        want = self._terms(check[None], rest_x)[0].numpy()
        got = np.empty_like(want)
        self._affine(check, got)
        if not np.allclose(got, want, rtol=1e-4, atol=1e-4):  # the module changed its steps
            raise ValueError("the module's frame planes are not affine per colour channel")

    def _affine(self, frame: np.ndarray, out: np.ndarray) -> None:
        """(S, S, 3) uint8 frame -> its (3, S, S) float32 planes, written into ``out``."""
        for c in range(3):
            np.copyto(out[c], self._offset[c])
            for k in np.flatnonzero(self._gain[:, c]):
                out[c] += frame[..., k] * self._gain[k, c]

    def _push(self, frame: np.ndarray) -> None:
        """Compute one (S, S, 3) uint8 frame's planes into the ring (slots i and i + T)."""
        phase = self._pushed % self.stride
        head = (self._heads[phase] + 1) % self.frames
        slots = self._slots[phase]
        if self.quantizer is None:
            self._affine(frame, slots[head])
        else:
            self._affine(frame, self._planes)
            self.quantizer(self._planes, out=slots[head])
        slots[head + self.frames] = slots[head]
        self._heads[phase], self._pushed = head, self._pushed + 1
