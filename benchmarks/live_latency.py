"""Live predictor latency per backend: one table row per backend/precision on this machine.

Target (reference-size model: 504k parameters, 256x256, T=15): sustained >= 30 Hz
with p99 latency <= 33 ms on the CPU; on a CUDA GPU >= 1000 readings/s at batch 1
with p99 <= 2 ms (CUDA graphs).

    .venv/bin/python benchmarks/live_latency.py                  # random reference-size model
    .venv/bin/python benchmarks/live_latency.py --checkpoint best.pt --frames 600 --json

Each row runs ``beadsight.live.bench.bench_live`` (simulated frames through
``PressurePredictor.update``): max throughput, sustained at --rate Hz, and the max
error vs fp32 torch in % of the peak. Backends that are not installed or not
supported here are listed as skipped; the CPU's bf16 rows appear only where bf16 is native.
"""

from __future__ import annotations

import argparse
import json
import sys

import torch

from beadsight.inference.machine import cpu_summary
from beadsight.inference.runtimes import BackendError, openvino_supports_bf16
from beadsight.live.bench import (
    add_model_arguments,
    bench_live,
    model_from_arguments,
    simulated_frames,
)

CPU_TARGET = {"hz": 30.0, "p99_ms": 33.0}
GPU_TARGET = {"hz": 1000.0, "p99_ms": 2.0}


def rows() -> list[tuple[str, str, str | None]]:
    """(backend, precision, device) rows to measure here. bf16 on the CPU only where it is
    native: emulated, torch bf16 took 13.6 s a reading at the reference size (AVX2 only)."""
    out = [("torch", "fp32", "cpu"), ("onnx", "fp32", None), ("openvino", "fp32", None)]
    if openvino_supports_bf16():
        out += [("torch", "bf16", "cpu"), ("openvino", "bf16", None)]
    if torch.cuda.is_available():
        out += [("cuda", "fp32", "cuda"), ("cuda", "bf16", "cuda")]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="frames per run")
    parser.add_argument("--rate", type=float, default=30.0, help="sustained run's Hz (0: skip)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--cache-dir", default=None, help="backend cache (default: none)")
    parser.add_argument("--json", action="store_true", help="one JSON object per row")
    add_model_arguments(parser)
    args = parser.parse_args(argv)
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)

    model = model_from_arguments(args)
    frames, source = simulated_frames(model.image_size, min(args.frames, 300))
    options = {"threads": args.threads, "cache_dir": args.cache_dir}
    if not args.json:
        print(
            f"model: {model.source} ({model.image_size} px, frames={model.frames}, span={model.span}); frames: {source}"
        )
        print(
            f"{'backend':16s} {'max Hz':>8s} {'p50 ms':>8s} {'p99 ms':>8s} {'max ms':>8s} "
            f"{'@' + format(args.rate, 'g') + 'Hz':>8s} {'p99 ms':>8s} {'err %':>8s}  target"
        )
    for name, precision, device in rows():
        try:
            result = bench_live(
                model,
                name,
                precision,
                args.frames,
                args.rate or None,
                device,
                options,
                source_frames=frames,
            )
        except (BackendError, ImportError, RuntimeError) as e:
            if args.json:
                print(json.dumps({"backend": f"{name}/{precision}", "skipped": str(e)}))
            else:
                print(f"{name + '/' + precision:16s} skipped: {e}")
            continue
        d = result.to_dict()
        target = GPU_TARGET if name == "cuda" else CPU_TARGET
        s = d["sustained"] or {}
        rate_ok = (
            (s.get("hz") or 0) >= 0.98 * target["hz"]
            if name != "cuda"
            else (d["hz"] >= target["hz"])
        )
        p99 = s.get("p99_ms") if name != "cuda" else d["p99_ms"]
        met = "met" if rate_ok and p99 is not None and p99 <= target["p99_ms"] else "missed"
        if args.json:
            print(json.dumps({**d, "target": target, "target_met": met == "met"}))
            continue
        print(
            f"{d['backend']:16s} {d['hz']:8.1f} {d['p50_ms']:8.2f} {d['p99_ms']:8.2f} "
            f"{d['max_ms']:8.2f} {s.get('hz') or float('nan'):8.1f} "
            f"{s.get('p99_ms') or float('nan'):8.2f} {d['max_abs_err_pct']:8.3f}  {met}"
        )
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
