"""End-to-end live rate: source -> preprocessing -> predictor -> listeners, as `beadsight live`.

Target: `beadsight live --source sim` keeps up with the 30 Hz camera (achieved rate >= 30
Hz, no skipped frames) with the reference-size model, and reports its latency
(capture timestamp -> reading available) percentiles.

    .venv/bin/python benchmarks/live_rate.py                      # tiny + reference-size models
    .venv/bin/python benchmarks/live_rate.py --checkpoint src/beadsight/assets/sim_model.pt
    .venv/bin/python benchmarks/live_rate.py --viewer --seconds 20 --json

Each row runs a LiveSensor on the simulator (paced at --fps) for --seconds after the
window has filled, optionally with the web viewer and one browser-like SSE client
(--viewer; ROS 2 and Foxglove: benchmarks/live_outputs.py), and prints readings/s,
source frames/s, frames skipped because inference was slower than the camera, and
latency / inference-time percentiles. Models without --checkpoint have random weights
(same cost as trained ones).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import urllib.request

import numpy as np
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel, load_checkpoint
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.inference.machine import cpu_summary
from beadsight.live.sensor import LiveSensor
from beadsight.live.settings import LiveSettings

MODELS = {  # name -> (image size px, U-Net width, frames)
    "tiny": (64, 8, 15),
    "reference": (256, 16, 15),
}


def random_model(size: int, width: int, frames: int) -> PressureModel:
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(frames=frames, width=width),
        geometry=SensorGeometry(image_size_px=size),
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
    )
    return PressureModel.create(meta)


def _sse_client(url: str, stop: threading.Event, counter: list[int]) -> None:
    with urllib.request.urlopen(url + "events") as events:
        while not stop.is_set():
            line = events.readline()
            if not line:
                return
            if line.startswith(b"data: "):
                counter[0] += 1


def run(name: str, model: PressureModel, args: argparse.Namespace) -> dict:
    rows: list[tuple[float, float, float]] = []  # (arrival, latency, inference)
    recording = threading.Event()

    def on_update(update) -> None:
        if recording.is_set():
            rows.append((time.monotonic(), update.latency_s, update.reading.latency_s))

    settings = LiveSettings(backend=args.backend, precision=args.precision, source_fps=args.fps)
    sensor = LiveSensor(model, "sim", settings)
    sensor.on_update(on_update)
    stop, threads, servers = threading.Event(), [], []
    sse_count = [0]
    with sensor:
        if args.viewer:
            from beadsight.live.outputs.viewer.server import ViewerServer

            servers.append(ViewerServer(sensor, port=0))
            threads.append(
                threading.Thread(target=_sse_client, args=(servers[-1].url, stop, sse_count))
            )
        for t in threads:
            t.start()
        while sensor.stats().readings < args.warmup:  # window filled, backend warm
            if sensor.wait(0.05):
                break
        skipped0 = sensor.stats().skipped_frames
        sse_count[0] = 0  # count only what arrives while timing
        recording.set()
        start = time.monotonic()
        sensor.wait(args.seconds)
        recording.clear()
        elapsed = time.monotonic() - start
        stats = sensor.stats()
        stop.set()
        for server in servers:
            server.close()
        for t in threads:
            t.join()
    if sensor.error is not None:
        raise sensor.error
    data = np.array(rows).reshape(-1, 3)
    lat = np.percentile(data[:, 1], [50, 99]) * 1e3 if len(data) else [np.nan] * 2
    inf = np.percentile(data[:, 2], [50, 99]) * 1e3 if len(data) else [np.nan] * 2
    return {
        "model": name,
        "image_size": model.image_size,
        "width": model.meta.model.width,
        "backend": sensor.predictor.backend.describe(),
        "readings_per_s": len(data) / elapsed,
        "source_fps": args.fps,
        "skipped_frames": stats.skipped_frames - skipped0,
        "latency_p50_ms": float(lat[0]),
        "latency_p99_ms": float(lat[1]),
        "inference_p50_ms": float(inf[0]),
        "inference_p99_ms": float(inf[1]),
        "viewer_messages_per_s": sse_count[0] / elapsed if args.viewer else None,
        "seconds": elapsed,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--checkpoint", default=None, help="benchmark this checkpoint instead")
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--precision", default="auto")
    parser.add_argument("--fps", type=float, default=30.0, help="simulated camera rate")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--warmup", type=int, default=30, help="readings before timing")
    parser.add_argument("--viewer", action="store_true", help="serve the viewer to one client")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)
    if args.checkpoint:
        targets = [(args.checkpoint, load_checkpoint(args.checkpoint))]
    else:
        targets = [(name, random_model(*MODELS[name])) for name in args.models]
    results = [run(name, model, args) for name, model in targets]
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print(
        f"live rate on the simulator at {args.fps:g} fps, {args.seconds:g} s per row "
        f"(viewer: {args.viewer}); torch threads {torch.get_num_threads()}"
    )
    head = (
        f"{'model':<28} {'backend':<18} {'Hz':>6} {'skipped':>7} {'lat p50':>8} "
        f"{'lat p99':>8} {'inf p50':>8} {'inf p99':>8}"
    )
    print(head)
    for r in results:
        print(
            f"{r['model'][:28]:<28} {r['backend'][:18]:<18} {r['readings_per_s']:6.1f} "
            f"{r['skipped_frames']:7d} {r['latency_p50_ms']:8.1f} {r['latency_p99_ms']:8.1f} "
            f"{r['inference_p50_ms']:8.1f} {r['inference_p99_ms']:8.1f}"
        )
    print("latency: capture timestamp -> reading available (ms); inf: predictor time (ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
