"""Training-loader throughput (windows/s) against the training step's samples/s.

Writes a dataset with :class:`beadsight.data.dataset_writer.DatasetWriter` into a temporary
folder (default 20 presses x 150 frames of 256x256 textured frames), then measures:

* **host** mode: ``WindowDataset`` + DataLoader workers reading each window as one
  contiguous HDF5 slice, labels rendered in the workers, D4 on the batch;
* **device** mode: all frames in one uint8 tensor on the device (load time
  reported separately); windows gathered by index arithmetic, labelled and D4-
  transformed on the device;
* the training step (:func:`beadsight.train.step.optimizer_step`, reference model width
  16, 15 frames) in fp32 and bf16 on batches from the loader,

and prints each loader's rate as a multiple of the training rate (target: >= 10x).

Usage::

    .venv/bin/python benchmarks/loader.py [--device cpu|cuda] [--presses 20] [--press-frames 150]
        [--batch 8] [--workers 0 2] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from train_speed import (  # sibling script (benchmarks/ is on sys.path)
    DTYPES,
    make_step,
    samples_per_s,
    sync,
)

from beadsight.config import SensorGeometry
from beadsight.data.dataset import open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.splits import window_ends
from beadsight.inference.machine import cpu_summary
from beadsight.train.windows import (
    DeviceFrames,
    DeviceWindows,
    WindowDataset,
    WindowLabels,
    WindowLoader,
    window_frame_mask,
)

FRAMES_PER_WRITE = 50


def write_dataset(path: Path, presses: int, frames_per_press: int, size: int, seed: int) -> Path:
    """Textured frames (smooth random pattern + noise + a dark blob under the finger)."""
    geometry = SensorGeometry(image_size_px=size)
    rng = np.random.default_rng(seed)
    phase = np.linspace(0, 1, frames_per_press)
    profile = np.clip(np.sin(np.pi * (phase - 0.2) / 0.6), 0, None) * (
        (phase > 0.2) & (phase < 0.8)
    )
    rows, cols = np.mgrid[0:size, 0:size]
    base = cv2.GaussianBlur(rng.integers(0, 256, (size, size, 3), dtype=np.uint8), (0, 0), 3)
    t0 = 1.7e9
    with DatasetWriter(path, geometry, provenance={"source": "benchmarks/loader.py"}) as w:
        for p in range(presses):
            xy = rng.uniform(-geometry.press_range_mm, geometry.press_range_mm, 2)
            force = rng.uniform(5, 20) * profile
            r, c = (0.5 - xy[1] / 41) * size, (0.5 - xy[0] / 41) * size
            blob = np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * (size / 13) ** 2))
            for a in range(0, frames_per_press, FRAMES_PER_WRITE):
                f = force[a : a + FRAMES_PER_WRITE]
                noise = rng.normal(0, 4, (len(f), size, size, 3))
                frames = base[None] - 6.0 * f[:, None, None, None] * blob[None, ..., None] + noise
                n = len(f)
                w.append(
                    np.clip(frames, 0, 255).astype(np.uint8),
                    f,
                    np.tile(xy, (n, 1)),
                    np.ones(n, bool),
                    t0 + (p * frames_per_press + a + np.arange(n)) / 30.0,
                )
    return path


def loader_rate(loader: WindowLoader, max_batches: int, device: torch.device) -> float:
    """Windows/s over up to ``max_batches`` batches, after one warm-up batch."""
    loader.set_epoch(0)
    it = iter(loader)
    next(it)  # warm-up (worker start-up, first reads)
    sync(device)
    start, windows = time.perf_counter(), 0
    for i, (frames, _) in enumerate(it):
        windows += len(frames)
        if i + 1 >= max_batches:
            break
    sync(device)
    return windows / (time.perf_counter() - start)


def train_rate(batches: list, device: torch.device, precision: str, args) -> float:
    step = make_step(args, device, precision)
    timed = batches[1 : 1 + args.train_steps]
    return samples_per_s(step, batches[:1], timed, args.batch, device)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--presses", type=int, default=20)
    p.add_argument("--press-frames", type=int, default=150, help="frames per press")
    p.add_argument("--size", type=int, default=256, help="dataset image size (px)")
    p.add_argument("--frames", type=int, default=15, help="frames per window (stride 1)")
    p.add_argument("--width", type=int, default=16, help="U-Net width for the training rate")
    p.add_argument("--up-kernel", type=int, default=1)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="host-mode worker counts")
    p.add_argument("--max-batches", type=int, default=60, help="batches timed per loader")
    p.add_argument("--train-steps", type=int, default=3, help="timed training steps per precision")
    p.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=list(DTYPES))
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument(
        "--dataset", type=Path, default=None, help="use this dataset instead of writing one"
    )
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory(prefix="beadsight-loader-") as tmp:
        path = args.dataset
        t = time.perf_counter()
        if path is None:
            path = write_dataset(
                Path(tmp) / "bench.h5", args.presses, args.press_frames, args.size, 0
            )
        write_s = time.perf_counter() - t
        result = run(args, path, device)
        result["dataset_write_s"] = write_s
    if args.json:
        print(json.dumps(result))
        return
    print(
        f"dataset: {result['frames']} frames {result['size']}x{result['size']}, "
        f"{result['windows']} windows of {args.frames} frames; device {device}, batch {args.batch}"
    )
    for name, rate in result["loader_windows_per_s"].items():
        ratios = ", ".join(f"{r:.0f}x {p}" for p, r in result["ratio_to_training"][name].items())
        print(f"  loader {name:<16} {rate:10.1f} windows/s   ({ratios} training rate)")
    print(f"  device-mode frame load: {result['device_load_frames_per_s']:.0f} frames/s")
    for precision, rate in result["train_samples_per_s"].items():
        print(f"  training step {precision}: {rate:.2f} samples/s (width {args.width})")


def run(args, path: Path, device: torch.device) -> dict:
    with open_dataset(path) as ds:
        ends = window_ends(ds.press_id, ds.valid, args.frames)
        labels = WindowLabels.from_dataset(ds, ends, ds.image_size)
        mask = window_frame_mask(ends, args.frames, len(ds))
        t = time.perf_counter()
        store = DeviceFrames.load(ds, mask, ds.image_size, device, progress=False)
        sync(device)
        load_s = time.perf_counter() - t
        frames_total, size = len(ds), ds.image_size
    args.size = size
    common = dict(device=device, shuffle=True, augment=True, seed=0)
    rates = {}
    device_loader = WindowLoader(DeviceWindows(store, labels, args.frames), args.batch, **common)
    rates["device"] = loader_rate(device_loader, args.max_batches, device)
    for workers in args.workers:
        host = WindowLoader(
            WindowDataset(path, labels, args.frames), args.batch, num_workers=workers, **common
        )
        rates[f"host/{workers} workers"] = loader_rate(host, args.max_batches, device)
    device_loader.set_epoch(0)
    it = iter(device_loader)
    batches = [next(it) for _ in range(args.train_steps + 1)]
    train = {
        p: train_rate(batches, device, p, args)
        for p in args.precisions
        if p != "fp16" or device.type == "cuda"
    }
    return {
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "frames": frames_total,
        "size": size,
        "windows": len(labels),
        "batch": args.batch,
        "loader_windows_per_s": rates,
        "device_load_frames_per_s": int(mask.sum()) / load_s,
        "train_samples_per_s": train,
        "ratio_to_training": {n: {p: r / t for p, t in train.items()} for n, r in rates.items()},
    }


if __name__ == "__main__":
    main()
