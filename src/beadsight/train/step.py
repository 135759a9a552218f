"""One optimizer step of the reference recipe, and the network input it is computed on.

Used by the trainer and, unchanged, by the benchmarks that time training
(``benchmarks/train_speed.py``, ``benchmarks/loader.py``).
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import torch
import torch.nn.functional as F

from beadsight.train.augment import color_jitter as jitter


def model_inputs(
    module, frames: torch.Tensor, noise_std: float = 0.0, color_jitter: float = 0.0
) -> torch.Tensor:
    """(B, inputs, S, S, 3) uint8 RGB -> (B, C, S, S) float32 normalised network input,
    after colour jitter of strength ``color_jitter`` and plus Gaussian noise of
    ``noise_std`` (pass 0 for both for validation and inference)."""
    if color_jitter > 0:
        frames = jitter(frames, color_jitter)
    x = module.normalize(frames)
    if noise_std > 0:
        x = x + noise_std * torch.randn_like(x)
    return x


def autocast(device: torch.device, dtype: torch.dtype | None) -> AbstractContextManager:
    """Autocast to ``dtype`` (bf16/fp16) on ``device``'s type; None: a no-op context."""
    if dtype is None:
        return nullcontext()
    return torch.autocast(torch.device(device).type, dtype=dtype)


def optimizer_step(
    module,
    net: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    frames: torch.Tensor,
    targets: torch.Tensor,
    *,
    output_scale_kpa: float,
    noise_std: float,
    color_jitter: float = 0.0,
    autocast_dtype: torch.dtype | None = None,
    scaler: torch.amp.GradScaler | None = None,
) -> torch.Tensor:
    """One training step; returns the (detached, not synchronised) loss.

    module: the FramesToPressure (normalisation); net: its U-Net, or the U-Net
    wrapped in DDP. frames: (B, T, S, S, 3) uint8 RGB; targets: (B, S, S) kPa.
    Loss: MSE between the network output and ``targets / output_scale_kpa``.
    """
    x = model_inputs(module, frames, noise_std, color_jitter)
    with autocast(frames.device, autocast_dtype):
        out = net(x)  # (B, 1, S, S)
    loss = F.mse_loss(out[:, 0].float(), targets / output_scale_kpa)
    optimizer.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
    else:
        loss.backward()
        optimizer.step()
    return loss.detach()
