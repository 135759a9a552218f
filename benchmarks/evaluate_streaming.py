"""Evaluation throughput and memory: does `evaluate` stay bounded as the dataset grows?

Builds a synthetic dataset, then evaluates an untrained model (same architecture
as a real one, any width) on growing numbers of frames with predictions.h5 and
plots written. Prints frames/s and the peak of Python/numpy allocations
(tracemalloc) during each run: with streaming evaluation the peak must not
grow with the number of frames.

    .venv/bin/python benchmarks/evaluate_streaming.py [--image-size 128] [--frames 100 400]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.inference.machine import cpu_summary

FRAMES_PER_PRESS = 60
MIB = 2**20


def make_dataset(path: Path, presses: int, geometry: SensorGeometry, seed: int = 0) -> Path:
    """Force ramps at random positions; frames are noise darkened under the finger."""
    rng = np.random.default_rng(seed)
    s = geometry.image_size_px
    phase = np.linspace(0, 1, FRAMES_PER_PRESS)
    shape = np.clip(np.sin(np.pi * (phase - 0.2) / 0.6), 0, None) * ((phase > 0.2) & (phase < 0.8))
    with DatasetWriter(path, geometry, fps=30) as w:
        for p in range(presses):
            force = rng.uniform(5, 20) * shape
            xy = rng.uniform(-geometry.press_range_mm, geometry.press_range_mm, 2)
            frames = rng.integers(60, 200, (FRAMES_PER_PRESS, s, s, 3), dtype=np.uint8)
            t = 1.7e9 + (p * FRAMES_PER_PRESS + np.arange(FRAMES_PER_PRESS)) / 30
            w.append(
                frames,
                force,
                np.tile(xy, (FRAMES_PER_PRESS, 1)),
                np.ones(FRAMES_PER_PRESS, bool),
                t,
            )
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--width", type=int, default=8)
    parser.add_argument("--frames", type=int, nargs="+", default=[100, 400])
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--json", action="store_true", help="print results as JSON")
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)

    geometry = SensorGeometry(image_size_px=args.image_size)
    meta = CheckpointMeta(
        model=ModelConfig(frames=15, width=args.width),
        geometry=geometry,
        pixel_mean=[128.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=10.0,
    )
    torch.manual_seed(0)
    model = PressureModel.create(meta)
    ends_per_press = FRAMES_PER_PRESS - 14
    presses = -(-max(args.frames) // ends_per_press)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        data = make_dataset(Path(tmp) / "bench.h5", presses, geometry)
        for n in args.frames:
            tracemalloc.start()
            start = time.perf_counter()
            settings = EvaluateConfig(
                split="all",
                batch_size=args.batch_size,
                device=args.device,
                max_frames=n,
                progress=False,
            )
            metrics = evaluate(model, data, settings, Path(tmp) / f"eval{n}")
            seconds = time.perf_counter() - start
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            size = (Path(tmp) / f"eval{n}" / "predictions.h5").stat().st_size
            results.append(
                {
                    "frames": metrics["frames"],
                    "seconds": round(seconds, 2),
                    "frames_per_s": round(metrics["frames"] / seconds, 1),
                    "peak_alloc_mib": round(peak / MIB, 1),
                    "predictions_h5_mib": round(size / MIB, 2),
                    "device": metrics["device"],
                }
            )
    if args.json:
        print(json.dumps({"image_size": args.image_size, "width": args.width, "runs": results}))
    else:
        print(
            f"evaluate streaming, {args.image_size}x{args.image_size} px, U-Net width "
            f"{args.width}, batch {args.batch_size}"
        )
        for r in results:
            print(
                f"  {r['frames']:6d} frames: {r['seconds']:7.2f} s  {r['frames_per_s']:7.1f} "
                f"frames/s  peak alloc {r['peak_alloc_mib']:7.1f} MiB  predictions.h5 "
                f"{r['predictions_h5_mib']:.2f} MiB  ({r['device']})"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
