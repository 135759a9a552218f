"""Processing throughput and memory: raw 1280x1024 MJPG recording -> dataset.

Target: >= 300 frames/s for 1280x1024 input, and peak memory that does not grow with
the recording's length (a 1-hour recording, 108,000 frames, in < 2 GB).

The script synthesizes a raw recording in this project's format: one chunk of
``--unique`` distinct raw fisheye frames rendered by the simulator
(``PouchSimulator.render_raw``, a finger pressing into the pouch) is encoded once and
hard-linked as every further chunk, while the frame, force (80 Hz) and printer logs
cover the whole duration with a press every 10 s. Every frame is still decoded and
preprocessed. Each processing run happens in a fresh subprocess, so its peak RSS
(``ru_maxrss``) is the processing's own. It runs two lengths (``--frames`` and half of
it): equal peak memory means memory is bounded whatever the length.

    .venv/bin/python benchmarks/process_speed.py [--frames 3000] [--json]
    .venv/bin/python benchmarks/process_speed.py --frames 108000 --image-size 64  # one hour
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from beadsight.config import REFERENCE_CENTRE_XY_MM
from beadsight.inference.machine import cpu_summary

FPS = 30.0
SCALE_HZ = 80.0
PRESS_PERIOD_S = 10.0
CENTRE = REFERENCE_CENTRE_XY_MM
G_TO_N = 9.81e-3


def _unique_frames(count: int, seed: int = 0) -> list[np.ndarray]:
    """Raw BGR fisheye frames of a press, from the simulator (synthetic if unavailable)."""
    try:
        from beadsight.sim import PouchSimulator
    except ImportError:  # pragma: no cover - simulator not installed
        rng = np.random.default_rng(seed)
        import cv2

        base = cv2.GaussianBlur(rng.integers(0, 256, (1024, 1280, 3), dtype=np.uint8), (0, 0), 3)
        return [np.roll(base, 3 * k, axis=1) for k in range(count)]
    sim = PouchSimulator(seed=seed)
    frames = []
    for k in range(count):
        depth = 1.5 * np.sin(np.pi * k / max(count - 1, 1))
        sim.step(1 / FPS, (2.0, -1.5), depth)
        frames.append(sim.render_raw())
    return frames


def synthesize(raw: Path, frames: int, unique: int) -> None:
    """Write a raw recording of ``frames`` frames (see the module docstring)."""
    from beadsight.data.recording import FRAMES_FILE, VIDEO_NAME, RecordingWriter
    from beadsight.devices.base import CommandRecord, ScaleReading

    images = _unique_frames(unique)
    t0_unix, t0_mono = 1.7e9, 1000.0
    duration = frames / FPS
    meta = {"virtual": True, "centre_xy_mm": list(CENTRE), "note": "benchmark"}
    with RecordingWriter(raw, meta, frame_hw=(1024, 1280), fps=FPS, chunk_frames=unique) as w:
        for k, image in enumerate(images):
            w.write_frame(image, t_unix=t0_unix + k / FPS, t_mono=t0_mono + k / FPS, camera_index=k)
        t = np.arange(0.05, duration, 1 / SCALE_HZ)
        phase = (t % PRESS_PERIOD_S) / PRESS_PERIOD_S
        force = (
            8.0
            * np.clip(np.sin(np.pi * (phase - 0.3) / 0.4), 0, None)
            * (phase > 0.3)
            * (phase < 0.7)
        )
        w.write_readings(
            ScaleReading(t0_unix + ti, t0_mono + ti, round(f / G_TO_N, 2), f, i, None)
            for i, (ti, f) in enumerate(zip(t, force, strict=True))
        )
        rng = np.random.default_rng(1)
        for p in range(int(np.ceil(duration / PRESS_PERIOD_S))):
            ts = p * PRESS_PERIOD_S
            x, y = CENTRE[0] + rng.uniform(-13.75, 13.75), CENTRE[1] + rng.uniform(-13.75, 13.75)
            w.write_command(
                CommandRecord(t0_unix + ts, t0_mono + ts, f"G1 X{x:.3f} Y{y:.3f}", x, y, 137.5),
                press=p,
            )
            w.write_command(
                CommandRecord(t0_unix + ts + 2, t0_mono + ts + 2, "G1 Z127.5", x, y, 127.5), press=p
            )
    first = raw / VIDEO_NAME.format(0)
    with open(raw / FRAMES_FILE, "a") as f:
        for k in range(unique, frames):
            chunk, index = divmod(k, unique)
            if index == 0:
                os.link(first, raw / VIDEO_NAME.format(chunk))
            f.write(f"{chunk},{index},{t0_unix + k / FPS!r},{t0_mono + k / FPS!r},{k}\n")
    # a partial last chunk links the full video: its extra frames are simply not logged


_CHILD = """
import json, resource, sys, time
from beadsight.inference.machine import cpu_summary
from beadsight.data.process.run import process_recording
from beadsight.data.process.config import ProcessConfig
config = ProcessConfig(**json.loads(sys.argv[3]))
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
t, c = time.perf_counter(), cpu()
qa = process_recording(sys.argv[1], sys.argv[2], config, progress=False)
print(json.dumps({"frames": qa["frames_written"], "seconds": time.perf_counter() - t,
                  "cpu_seconds": cpu() - c, "decode_scale": qa["decode_scale"],
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run_process(raw: Path, out: Path, config: dict) -> dict:
    res = subprocess.run(
        [sys.executable, "-c", _CHILD, str(raw), str(out), json.dumps(config)],
        capture_output=True,
        text=True,
        check=False,
    )
    if res.returncode != 0:
        raise SystemExit(f"processing failed:\n{res.stderr[-3000:]}")
    result = json.loads(res.stdout.strip().splitlines()[-1])
    result["frames_per_s"] = result["frames"] / result["seconds"]
    return result


def marginal(short: dict, long: dict) -> tuple[float, float]:
    """Frames/s and CPU ms/frame of the extra frames of the long run (fixed costs cancel:
    imports, building the remap table, QA plot)."""
    frames = long["frames"] - short["frames"]
    wall = long["seconds"] - short["seconds"]
    cpu = long["cpu_seconds"] - short["cpu_seconds"]
    return frames / wall if wall > 0 else float("nan"), 1000 * cpu / frames if frames else float(
        "nan"
    )


def stage_costs(raw: Path, config: dict, repeats: int = 3) -> dict[str, float]:
    """Single-thread CPU ms per frame of each stage, on the first chunk's frames."""
    import cv2

    from beadsight.config import SensorGeometry
    from beadsight.data.dataset_writer import DatasetWriter
    from beadsight.data.process.config import ProcessConfig
    from beadsight.data.process.images import DECODE_FLAGS
    from beadsight.data.recording import VIDEO_NAME, iter_video
    from beadsight.preprocess import Preprocessor

    cfg = ProcessConfig(**config)
    pre = Preprocessor.from_spec(
        cfg.preprocess,
        (1024, 1280),
        cfg.image_size,
        interpolation=cfg.interpolation,
        resize=cfg.resize,
    )
    factor = cfg.decode_scale or pre.max_reduction()
    if factor > 1:
        pre = pre.for_reduced_input(factor)
    packets = list(iter_video(raw / VIDEO_NAME.format(0), packets=True))
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_THREAD)
        return r.ru_utime + r.ru_stime

    try:
        n = len(packets) * repeats
        c = cpu()
        images = [cv2.imdecode(p, DECODE_FLAGS[factor]) for p in packets * repeats]
        decode = cpu() - c
        c = cpu()
        out = np.stack([pre(im) for im in images])
        remap = cpu() - c
        with tempfile.TemporaryDirectory() as tmp:
            geometry = SensorGeometry(image_size_px=cfg.image_size)
            with DatasetWriter(Path(tmp) / "d.h5", geometry) as w:
                c = cpu()
                for i in range(0, n, cfg.batch_frames):  # the batches process appends
                    b = out[i : i + cfg.batch_frames]
                    m = len(b)
                    w.append(b, np.zeros(m), np.zeros((m, 2)), np.ones(m, bool), np.zeros(m))
                append = cpu() - c
    finally:
        cv2.setNumThreads(threads)
    return {
        f"decode_jpeg_1/{factor}": 1000 * decode / n,
        "preprocess": 1000 * remap / n,
        "dataset_append": 1000 * append / n,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=3000, help="frames of the long run")
    parser.add_argument("--unique", type=int, default=30, help="distinct frames (one chunk)")
    parser.add_argument("--image-size", type=int, default=256)
    parser.add_argument("--interpolation", default="linear", choices=("linear", "reference"))
    parser.add_argument(
        "--resize", default="supersample", choices=("supersample", "area", "linear")
    )
    parser.add_argument("--decode-scale", type=int, default=0, choices=(0, 1, 2, 4, 8))
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--workdir", type=Path, default=None, help="where to write (default tmp)")
    parser.add_argument("--json", action="store_true", help="print one JSON line")
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)
    config = {
        "image_size": args.image_size,
        "interpolation": args.interpolation,
        "resize": args.resize,
        "decode_scale": args.decode_scale,
        "workers": args.workers,
    }
    with tempfile.TemporaryDirectory(dir=args.workdir) as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        lengths = sorted({max(args.unique, args.frames // 2), args.frames})
        for n in lengths:
            synthesize(tmp / f"raw_{n}", n, args.unique)
        synth_s = time.perf_counter() - t
        stages = stage_costs(tmp / f"raw_{lengths[0]}", config)
        results = {}
        for n in lengths:
            results[n] = run_process(tmp / f"raw_{n}", tmp / f"d_{n}.h5", config)
            (tmp / f"d_{n}.h5").unlink()
    short, long = results[lengths[0]], results[lengths[-1]]
    stream_fps, cpu_ms = marginal(short, long) if len(lengths) > 1 else (float("nan"),) * 2
    cores = os.cpu_count() or 1
    summary = {
        "input": "1280x1024 MJPG (simulated raw fisheye frames)",
        "config": config,
        "cpu_cores": cores,
        "load_average_1min": os.getloadavg()[0],
        "runs": {str(n): r for n, r in results.items()},
        "frames_per_s": long["frames_per_s"],
        "streaming_frames_per_s": stream_fps,
        "cpu_ms_per_frame": cpu_ms,
        "idle_machine_estimate_frames_per_s": cores * 1000 / cpu_ms,
        "peak_rss_mb": long["peak_rss_mb"],
        "peak_rss_growth_mb": long["peak_rss_mb"] - short["peak_rss_mb"],
        "synthesis_s": synth_s,
        "stage_cpu_ms_per_frame": stages,
    }
    if args.json:
        print(json.dumps(summary))
        return
    print(f"process: {summary['input']} -> {args.image_size}x{args.image_size}, {config}")
    print(
        f"machine: {cores} cores, 1-min load average {summary['load_average_1min']:.1f} "
        "(a busy machine slows the wall-clock figures)"
    )
    for n, r in results.items():
        print(
            f"  {n:>7} frames: {r['frames_per_s']:7.1f} frames/s overall ({r['seconds']:.1f} s), "
            f"peak RSS {r['peak_rss_mb']:.0f} MB, JPEG decoded at 1/{r['decode_scale']}"
        )
    print(
        f"streaming rate (extra frames of the long run): {stream_fps:.1f} frames/s wall, "
        f"{cpu_ms:.2f} CPU ms/frame -> {summary['idle_machine_estimate_frames_per_s']:.0f} "
        f"frames/s on {cores} idle cores"
    )
    print(
        "single-thread CPU ms per frame by stage: "
        + ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
    )
    print(
        f"peak RSS growth from {lengths[0]} to {lengths[-1]} frames: "
        f"{summary['peak_rss_growth_mb']:+.0f} MB"
    )


if __name__ == "__main__":
    main()
