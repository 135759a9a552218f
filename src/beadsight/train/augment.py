"""Training augmentation: the dihedral (D4) transforms, the 8 symmetries of the square,
applied identically to every frame of a training window and to its target map; and
colour jitter, one random colour change per window (rest image included)."""

from __future__ import annotations

import numpy as np
import torch

from beadsight.config import ConfigError

D4_ORDER = 8  # rotations by 0/90/180/270 degrees, each with and without a mirror

__all__ = ["D4_ORDER", "color_jitter", "d4_batch", "d4_transform", "index_on"]


def d4_transform(x, k: int, axes: tuple[int, int] = (0, 1)):
    """Apply dihedral transform ``k`` (0..7) to the two spatial ``axes`` of ``x``.

    ``k % 4`` quarter turns (``np.rot90``/``torch.rot90`` convention, counter-clockwise),
    then, for ``k >= 4``, a mirror along the second axis (``np.flip(axis=axes[1])``).
    Works on numpy arrays and torch tensors; the 8 values of ``k`` give the 8
    distinct symmetries of the square. Square images keep their shape.
    """
    if not 0 <= int(k) < D4_ORDER:
        raise ConfigError(f"D4 transform index must be in 0..7, got {k}")
    k = int(k)
    if isinstance(x, torch.Tensor):
        y = torch.rot90(x, k % 4, dims=axes)
        return torch.flip(y, dims=(axes[1],)) if k >= 4 else y
    y = np.rot90(x, k % 4, axes=axes)
    return np.flip(y, axis=axes[1]) if k >= 4 else y


def d4_batch(
    frames: torch.Tensor, targets: torch.Tensor, ks: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample D4 transforms of a batch, identical for all frames of a sample and its target.

    frames: (B, T, S, S, 3); targets: (B, S, S); ks: (B,) ints in 0..7.
    returns: transformed (frames, targets), same shapes, dtypes and device. One
    tensor operation per distinct ``k`` (at most 8), not per sample.
    """
    ks = np.asarray(ks)
    if (ks == 0).all():
        return frames, targets
    out_f = torch.empty_like(frames)
    out_t = torch.empty_like(targets)
    if (np.diff(ks) >= 0).all():  # sorted (as epoch_batches plans them): one slice per k
        bounds = np.flatnonzero(np.diff(ks)) + 1
        for a, b in zip([0, *bounds.tolist()], [*bounds.tolist(), len(ks)], strict=True):
            out_f[a:b] = d4_transform(frames[a:b], int(ks[a]), axes=(2, 3))
            out_t[a:b] = d4_transform(targets[a:b], int(ks[a]), axes=(1, 2))
        return out_f, out_t
    for k in np.unique(ks).tolist():
        sel = index_on(frames.device, np.flatnonzero(ks == k))
        out_f[sel] = d4_transform(frames.index_select(0, sel), k, axes=(2, 3))
        out_t[sel] = d4_transform(targets.index_select(0, sel), k, axes=(1, 2))
    return out_f, out_t


def index_on(device: torch.device, index: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Index array -> int64 tensor on ``device``; to a GPU through pinned memory without
    blocking, so gathering a batch does not wait for the GPU to finish earlier work."""
    idx = torch.as_tensor(index, dtype=torch.int64)
    if device.type == "cuda" and idx.device.type == "cpu":
        return idx.pin_memory().to(device, non_blocking=True)
    return idx.to(device)


# Colour augmentation at strength 1 (``TrainConfig.color_jitter``); each scales linearly.
JITTER_GAIN = 0.4  # per-channel gain: exp(+-0.4) = x0.67 .. x1.49
JITTER_CONTRAST = 0.5  # contrast about the image mean: exp(+-0.5) = x0.61 .. x1.65
JITTER_BRIGHTNESS = 30.0  # brightness offset, +- levels of 0..255
JITTER_SHUFFLE_P = 0.5  # chance of a random channel order (a bead colour becomes another)
JITTER_GRAY_P = 0.15  # chance of a gray image (monochrome beads)


def color_jitter(images: torch.Tensor, strength: float) -> torch.Tensor:
    """(B, N, H, W, 3) uint8 RGB -> (B, N, H, W, 3) float32 0..255 with one random colour
    change per sample, the same for all N images of it (window and rest alike): channel
    order, gray, per-channel gain, contrast and brightness. Draws from torch's global RNG.
    ``strength`` 0 returns the images as float unchanged."""
    x = images.to(torch.float32)
    if strength <= 0:
        return x
    b, dev = x.shape[0], x.device

    def uniform(*shape: int) -> torch.Tensor:
        return (torch.rand(*shape, device=dev) * 2 - 1) * strength

    perm = torch.stack([torch.randperm(3, device=dev) for _ in range(b)])  # (B, 3)
    keep = torch.rand(b, device=dev) >= JITTER_SHUFFLE_P * min(strength, 1.0)
    perm[keep] = torch.arange(3, device=dev)
    x = torch.gather(x, -1, perm.view(b, 1, 1, 1, 3).expand_as(x))
    gray = torch.rand(b, device=dev) < JITTER_GRAY_P * min(strength, 1.0)
    x = torch.where(gray.view(b, 1, 1, 1, 1), x.mean(-1, keepdim=True).expand_as(x), x)
    x = x * torch.exp(JITTER_GAIN * uniform(b, 1, 1, 1, 3))
    mean = x.mean(dim=(1, 2, 3, 4), keepdim=True)
    x = (x - mean) * torch.exp(JITTER_CONTRAST * uniform(b, 1, 1, 1, 1)) + mean
    x = x + JITTER_BRIGHTNESS * uniform(b, 1, 1, 1, 1)
    return x.clamp_(0.0, 255.0)
