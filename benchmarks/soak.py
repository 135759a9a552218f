"""Soak test: 100,000 simulated frames through PressurePredictor.update.

Targets: resident memory grows < 50 MB from the end of warm-up to the end, and
latency does not creep (the p50 of each 10k-frame block stays near the first).

    .venv/bin/python benchmarks/soak.py                       # reference size, auto backend
    .venv/bin/python benchmarks/soak.py --frames 20000 --backend openvino
    .venv/bin/python benchmarks/soak.py --image-size 64 --width 8   # quick, small model

Frames: a few hundred simulator frames rendered once and cycled (the renderer is
not what is being soaked). Frames are fed back to back with nominal 30 Hz
timestamps; every 7919th frame is skipped to exercise the dropped-frame path.
Prints RSS at start and end, and latency p50/p99 per block; exits 1 when memory
grew by 50 MB or more.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from beadsight.inference.machine import cpu_summary
from beadsight.inference.predictor import PressurePredictor
from beadsight.live.bench import add_model_arguments, model_from_arguments, simulated_frames

MAX_RSS_GROWTH_MB = 50.0
CREEP_LIMIT = 1.25  # later blocks' median p50 above this times the earlier blocks' is creep
WARMUP_READINGS = 200  # readings before the start RSS is taken (allocators, caches)
DROP_EVERY = 7919  # skip one frame in this many (a prime: never aligned with the blocks)
SOURCE_FRAMES = 300


def rss_mb() -> float:
    """Resident set size of this process, MB (Linux /proc; else peak RSS)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError):  # pragma: no cover - not Linux
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--block", type=int, default=10_000, help="frames per latency block")
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--precision", default="auto")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--json", action="store_true", help="print a JSON summary at the end")
    add_model_arguments(parser)
    args = parser.parse_args(argv)
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)

    model = model_from_arguments(args)
    frames, source = simulated_frames(model.image_size, SOURCE_FRAMES)
    predictor = PressurePredictor.from_checkpoint(
        model, args.backend, args.precision, threads=args.threads
    )
    print(f"soak: {args.frames} frames, {predictor!r}, frames from {source}", flush=True)
    period = predictor.frame_period_s
    latencies: list[float] = []
    blocks: list[dict] = []
    start_rss = None
    readings = 0
    t0 = time.perf_counter()
    for k in range(args.frames):
        if k % DROP_EVERY == DROP_EVERY - 1:
            continue
        reading = predictor.update(frames[k % len(frames)], k * period)
        if reading is not None:
            readings += 1
            latencies.append(reading.latency_s)
            if readings == WARMUP_READINGS:
                start_rss = rss_mb()
                print(f"RSS at start (after {WARMUP_READINGS} readings): {start_rss:.1f} MB")
        if (k + 1) % args.block == 0 or k + 1 == args.frames:
            lat = np.asarray(latencies) * 1e3
            blocks.append(
                {
                    "frames_done": k + 1,
                    "readings": len(lat),
                    "p50_ms": float(np.percentile(lat, 50)) if len(lat) else None,
                    "p99_ms": float(np.percentile(lat, 99)) if len(lat) else None,
                    "rss_mb": rss_mb(),
                }
            )
            b = blocks[-1]
            if b["readings"]:
                print(
                    f"frames {b['frames_done']:>7d}: p50 {b['p50_ms']:7.2f} ms  "
                    f"p99 {b['p99_ms']:7.2f} ms  RSS {b['rss_mb']:7.1f} MB",
                    flush=True,
                )
            latencies = []
    elapsed = time.perf_counter() - t0
    end_rss = rss_mb()
    start_rss = start_rss if start_rss is not None else end_rss
    growth = end_rss - start_rss
    p50s = [b["p50_ms"] for b in blocks if b["p50_ms"] is not None]
    half = len(p50s) // 2
    creep = (
        float(np.median(p50s[half:]) / np.median(p50s[:half])) if half else float("nan")
    )  # later blocks vs earlier blocks: robust to a single noisy block
    print(f"RSS at end: {end_rss:.1f} MB (growth {growth:+.1f} MB; limit {MAX_RSS_GROWTH_MB} MB)")
    print(
        f"latency creep: median p50 of the later / earlier half of the blocks = {creep:.2f} "
        f"({'ok' if creep <= CREEP_LIMIT else 'CREEP'}; limit {CREEP_LIMIT})"
    )
    print(
        f"{readings} readings in {elapsed:.1f} s ({readings / elapsed:.1f} readings/s), "
        f"dropped frames seen: {predictor.dropped_frames}"
    )
    if args.json:
        print(
            json.dumps(
                {
                    "frames": args.frames,
                    "readings": readings,
                    "rss_start_mb": start_rss,
                    "rss_end_mb": end_rss,
                    "rss_growth_mb": growth,
                    "creep": creep,
                    "blocks": blocks,
                    "backend": predictor.backend.describe(),
                }
            )
        )
    predictor.close()
    return 0 if growth < MAX_RSS_GROWTH_MB else 1


if __name__ == "__main__":
    sys.exit(main())
