"""The dihedral (D4) augmentation: the 8 symmetries of the square, applied identically
to every frame of a training window and to its target map."""

from __future__ import annotations

import numpy as np
import torch

from beadsight.config import ConfigError

D4_ORDER = 8  # rotations by 0/90/180/270 degrees, each with and without a mirror

__all__ = ["D4_ORDER", "d4_batch", "d4_transform", "index_on"]


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
