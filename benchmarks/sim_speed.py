"""Simulator speed: frames per second of rendering, raw fisheye frames, and whole sessions.

Target: >= 500 sensor-space frames/s at 256 x 256 on a 2-core CPU.

    .venv/bin/python benchmarks/sim_speed.py [--frames 600] [--repeats 3] [--json]

Figures (best of ``--repeats`` timed passes, after a warm-up that fills the sprite
cache, as in any session longer than a press or two):

* ``render_256`` / ``render_64``: ``render()`` of recorded pouch states (at rest and
  during presses), noise included, in frames per wall-clock second;
* ``raw``: ``render_raw()`` (1280 x 1024 fisheye, noise, MJPG) per second;
* ``session_256`` / ``session_64``: a :class:`SimulatedSession` (press trajectory,
  mechanics at frame and scale times, scale, rendering) per second;
* ``variety_256`` / ``variety_64``: the same with ``variety="train"`` and a new build
  (beads, light, camera, image; :mod:`beadsight.sim.variety`) every press, as a
  base-model training set is made (each new build starts an empty sprite cache);
* each also per CPU-second of this process (``*_cpu``): on a shared machine the
  wall-clock figure is what you get, the CPU figure what the code costs.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time

from beadsight.inference.machine import cpu_summary
from beadsight.sim import PouchSimulator, SimConfig, SimulatedSession


def cpu_model() -> str:
    """The processor's name (/proc/cpuinfo), for the record beside the figures."""
    from beadsight.inference.machine import cpu_name

    return cpu_name()


def _timed(fn, count: int, repeats: int) -> tuple[float, float]:
    """Best frames/s over ``repeats`` passes of ``fn(i)`` for i < count: (wall, cpu)."""
    best_wall, best_cpu = 0.0, 0.0
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        for i in range(count):
            fn(i)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        best_wall = max(best_wall, count / wall)
        best_cpu = max(best_cpu, count / max(cpu, 1e-9))
    return best_wall, best_cpu


def recorded_views(size: int, count: int, seed: int = 0):
    """Pouch states of a session with presses, and the simulator that made them."""
    session = SimulatedSession(SimConfig(image_size_px=size), seed, render=False)
    views = [session.simulator.view() for _ in itertools.islice(session, count)]
    return session.simulator, views


def bench_render(size: int, frames: int, repeats: int) -> tuple[float, float]:
    sim, views = recorded_views(size, frames)
    sim.render()  # builds the renderer
    renderer = sim._renderer
    for v in views:  # warm-up: fill the sprite cache
        renderer.render(v)
    return _timed(lambda i: renderer.render(views[i]), frames, repeats)


def bench_raw(frames: int, repeats: int) -> tuple[float, float]:
    sim = PouchSimulator(SimConfig(), seed=0)
    sim.step(1 / 30, (0.0, 0.0), -1.0)
    sim.render_raw()  # builds the maps and renderer

    def one(i: int) -> None:
        sim.step(1 / 30, (3.0, -2.0), 1.5 * min(i / frames * 2, 1.0))
        sim.render_raw()

    for i in range(frames):
        one(i)
    return _timed(one, frames, repeats)


def bench_session(
    size: int, frames: int, repeats: int, variety: str | None = None
) -> tuple[float, float]:
    per_pouch = None if variety is None else 1
    session = iter(
        SimulatedSession(
            SimConfig(image_size_px=size), seed=0, presses_per_pouch=per_pouch, variety=variety
        )
    )
    for _ in range(400):  # two presses: warm the sprite cache
        next(session)
    return _timed(lambda i: next(session), frames, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600, help="frames per timed pass")
    parser.add_argument("--raw-frames", type=int, default=40, help="raw frames per timed pass")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes (best is kept)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)

    results: dict[str, float | str] = {}
    for name, (wall, cpu) in (
        ("render_256", bench_render(256, args.frames, args.repeats)),
        ("render_64", bench_render(64, args.frames, args.repeats)),
        ("raw", bench_raw(args.raw_frames, args.repeats)),
        ("session_256", bench_session(256, args.frames, args.repeats)),
        ("session_64", bench_session(64, args.frames, args.repeats)),
        ("variety_256", bench_session(256, args.frames, args.repeats, "train")),
        ("variety_64", bench_session(64, args.frames, args.repeats, "train")),
    ):
        results[f"{name}_fps"] = round(wall, 1)
        results[f"{name}_cpu_fps"] = round(cpu, 1)
    results["cpu_count"] = os.cpu_count() or 0
    results["cpu_model"] = cpu_model()
    results["load_average_1min"] = round(os.getloadavg()[0], 2)
    frames_per_press = SimulatedSession(SimConfig(), 0, presses=20, render=False).num_frames() / 20
    results["frames_per_press"] = round(frames_per_press, 1)
    if args.json:
        print(json.dumps(results))
        return
    print(
        f"simulator speed ({results['cpu_count']} x {results['cpu_model']}, load average "
        f"{results['load_average_1min']}); frames/s wall-clock (per CPU-second)"
    )
    labels = {
        "render_256": "render() 256 x 256",
        "render_64": "render() 64 x 64",
        "raw": "render_raw() 1280 x 1024 fisheye",
        "session_256": "session (physics + render) 256",
        "session_64": "session (physics + render) 64",
        "variety_256": "session, new build every press, 256",
        "variety_64": "session, new build every press, 64",
    }
    for key, label in labels.items():
        print(f"  {label:<34} {results[key + '_fps']:>8.1f}  ({results[key + '_cpu_fps']:.1f})")
    target = "met" if results["render_256_fps"] >= 500 else "NOT met"
    print(f"  target >= 500 frames/s at 256: {target}")
    print(f"  frames per simulated press (30 fps, mean of 20): {frames_per_press:.1f}")


if __name__ == "__main__":
    main()
