"""Training throughput and batch-1 inference latency of the reference U-Net.

Measures, on synthetic frames (the model's cost does not depend on content):

* training samples/s (one optimizer step = normalise + noise + forward + MSE +
  backward + AdamW, exactly :func:`beadsight.train.step.optimizer_step`) in fp32 and
  bf16 autocast;
* eager batch-1 inference latency (uint8 frames in, kPa map out) in fp32 and bf16.

Usage::

    .venv/bin/python benchmarks/train_speed.py                 # CPU, 256 px, width 16, 15 frames
    .venv/bin/python benchmarks/train_speed.py --device cuda --batch 64
    .venv/bin/python benchmarks/train_speed.py --size 128 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.labels import label_maps
from beadsight.inference.machine import cpu_summary
from beadsight.train.step import autocast, optimizer_step

DTYPES = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def make_model(args, device: torch.device) -> PressureModel:
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(frames=args.frames, width=args.width, up_kernel=args.up_kernel),
        geometry=SensorGeometry(image_size_px=args.size),
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=1.2,
    )
    return PressureModel.create(meta).to(device)


def make_batch(args, batch: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    frames = torch.randint(
        0, 256, (batch, args.frames, args.size, args.size, 3), generator=g, dtype=torch.uint8
    )
    rng = np.random.default_rng(0)
    targets = label_maps(
        rng.uniform(1, 20, batch),
        rng.uniform(-13, 13, (batch, 2)),
        np.ones(batch, bool),
        SensorGeometry(image_size_px=args.size),
    )
    return frames.to(device), torch.from_numpy(targets).to(device)


def make_step(args, device: torch.device, precision: str):
    """One AdamW training step of a fresh model: ``step(frames, targets) -> loss``."""
    module = make_model(args, device).module.train()
    optimizer = torch.optim.AdamW(module.net.parameters(), lr=1e-4, weight_decay=1e-4)
    scaler = torch.amp.GradScaler("cuda") if precision == "fp16" else None

    def step(frames, targets):
        return optimizer_step(
            module,
            module.net,
            optimizer,
            frames,
            targets,
            output_scale_kpa=1.2,
            noise_std=0.05,
            autocast_dtype=DTYPES[precision],
            scaler=scaler,
        )

    return step


def samples_per_s(step, warmup: list, timed: list, batch: int, device: torch.device) -> float:
    """Training samples/s of ``step(frames, targets)`` over the ``timed`` (frames, targets)
    batches of ``batch`` samples, after a step on each of the ``warmup`` ones."""
    for frames, targets in warmup:
        step(frames, targets)
    sync(device)
    start = time.perf_counter()
    for frames, targets in timed:
        loss = step(frames, targets)
    loss.item()
    sync(device)
    return len(timed) * batch / (time.perf_counter() - start)


def train_rate(args, device: torch.device, precision: str) -> float:
    batch = make_batch(args, args.batch, device)
    step = make_step(args, device, precision)
    return samples_per_s(step, [batch] * args.warmup, [batch] * args.steps, args.batch, device)


@torch.inference_mode()
def latency_ms(args, device: torch.device, precision: str) -> dict[str, float]:
    module = make_model(args, device).module.eval()
    frames, _ = make_batch(args, 1, device)
    times = []
    for i in range(args.warmup + args.latency_runs):
        sync(device)
        start = time.perf_counter()
        with autocast(device, DTYPES[precision]):
            out = module(frames)
        out.float().cpu()
        if i >= args.warmup:
            times.append((time.perf_counter() - start) * 1e3)
    times.sort()
    return {"median_ms": statistics.median(times), "p90_ms": times[int(0.9 * (len(times) - 1))]}


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument("--size", type=int, default=256, help="image size in px")
    p.add_argument("--width", type=int, default=16)
    p.add_argument("--frames", type=int, default=15, help="T, frames the network sees")
    p.add_argument("--up-kernel", type=int, default=1)
    p.add_argument("--batch", type=int, default=8, help="training batch")
    p.add_argument("--steps", type=int, default=3, help="timed training steps per precision")
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--latency-runs", type=int, default=10)
    p.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=list(DTYPES))
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(
        ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    )
    result = {
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "torch_threads": torch.get_num_threads(),
        "size": args.size,
        "width": args.width,
        "frames": args.frames,
        "batch": args.batch,
        "train_samples_per_s": {},
        "inference_latency_batch1": {},
    }
    for precision in args.precisions:
        if precision == "fp16" and device.type != "cuda":
            continue
        result["train_samples_per_s"][precision] = train_rate(args, device, precision)
        result["inference_latency_batch1"][precision] = latency_ms(args, device, precision)
    if args.json:
        print(json.dumps(result))
        return
    print(
        f"device {result['device']} ({result['torch_threads']} torch threads), "
        f"{args.size}x{args.size}, width {args.width}, frames {args.frames}"
    )
    for precision, rate in result["train_samples_per_s"].items():
        lat = result["inference_latency_batch1"][precision]
        print(
            f"  {precision}: training {rate:8.2f} samples/s (batch {args.batch})   "
            f"inference batch 1: median {lat['median_ms']:8.1f} ms, p90 {lat['p90_ms']:8.1f} ms"
        )


if __name__ == "__main__":
    main()
