"""How much of the live force error is the rest image: the live pipeline against the same
model given the offline rest, on the live simulator's presses.

    PYTHONPATH=src .venv/bin/python benchmarks/live_rest.py [--checkpoint C] [--seeds 0 1 2 3]
        [--readings 3600] [--backend openvino] [--json]

For each seed, the simulator's session (what ``beadsight live --source sim --seed S`` plays)
is read two ways, one reading per frame with capture stamps one frame period apart, so a
run repeats exactly on any machine:

* ``live``: the default live pipeline (:class:`~beadsight.live.sensor.LiveSensor` with
  default settings but the backend): the rest reference taken at start-up and refreshed
  when the pouch reads unloaded and still (:mod:`beadsight.health.rest`);
* ``offline_rest``: the same frames through the same runtime, with the rest image that
  ``evaluate`` and training give each window (:func:`beadsight.data.rest.rest_ends` on the
  simulator's true force: the pouch as it last was unloaded, up to the frame before a
  press). No live pipeline can know the true force; this is the ceiling of any rest policy.

Each row gives the figures of ``benchmarks/live_response.py`` (force error over in-contact
readings, onset and release lag of the 1 N crossing in ms, readings of 1 N or more at a
true 0 N); the last rows are their means over the seeds. The last line is a JSON object
(--json: the only line).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib.util
import itertools
import json
import time
from pathlib import Path

import numpy as np

FPS = 30.0
FIGURES = {  # live_response.py's figure -> its column in the table
    "presses": "presses",
    "force_error_pct": "force err %",
    "onset_lag_ms_median": "onset med",
    "onset_lag_ms_max": "onset max",
    "release_lag_ms_median": "release med",
    "release_lag_ms_max": "release max",
    "unloaded_over_1n_pct": "0 N read >= 1 N %",
}


@functools.cache
def _response():
    """benchmarks/live_response.py's ``response`` (a sibling script, not a package)."""
    spec = importlib.util.spec_from_file_location(
        "live_response", Path(__file__).with_name("live_response.py")
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.response


def read_live(model, seed: int, readings: int, backend: str) -> np.ndarray:
    """(N, 4) frame time s (the session's frame index / fps), published N, true N, latency s
    of the default live pipeline."""
    from beadsight.devices.clock import FrameClock
    from beadsight.devices.virtual.camera import SimCamera
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    camera = SimCamera(
        model.image_size, seed=seed, realtime=False, queue_frames=1, clock=FrameClock(FPS)
    )
    settings = LiveSettings(backend=backend, max_readings=readings)
    sensor = LiveSensor(model, camera, settings).open()
    stream = sensor.updates(maxsize=readings + 1)
    rows = []
    with sensor:
        for u in stream:
            r = u.reading
            rows.append((u.source_index / FPS, r.force_n, u.reference_force_n, r.latency_s))
    return np.asarray(rows, dtype=np.float64).reshape(-1, 4)


def read_offline_rest(model, seed: int, frames: int, backend: str) -> np.ndarray:
    """The same session's first ``frames`` frames, each window beside its offline rest."""
    from beadsight.data.rest import REST_FRAMES, rest_ends
    from beadsight.inference.predictor import PredictorSettings, PressurePredictor
    from beadsight.inference.select import build_backend
    from beadsight.sim.config import SimConfig
    from beadsight.sim.session import SimulatedSession

    config = dataclasses.replace(SimConfig(), image_size_px=model.image_size, fps=FPS)
    records = list(itertools.islice(SimulatedSession(config, seed, None), frames))
    images = np.stack([r.frame_rgb for r in records])
    true_n = np.array([r.true_force_n for r in records], dtype=np.float64)
    rest_at = rest_ends(true_n, np.ones(len(true_n), dtype=bool))
    runtime = build_backend(model, backend, "fp32", cache_dir=None)
    predictor = PressurePredictor(model, runtime, settings=PredictorSettings(on_gap="ignore"))
    rows, current = [], -1
    try:
        for k in range(len(images)):
            if rest_at[k] < 0:
                continue
            if rest_at[k] != current:
                current = int(rest_at[k])
                predictor.set_rest(images[current - REST_FRAMES + 1 : current + 1])
            reading = predictor.update(images[k], k / FPS)
            if reading is not None:
                rows.append((k / FPS, reading.force_n, true_n[k], reading.latency_s))
    finally:
        predictor.close()
    return np.asarray(rows, dtype=np.float64).reshape(-1, 4)


def figures(rows: np.ndarray) -> dict:
    r = _response()(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3])
    return {k: r[k] for k in FIGURES}


def compare(checkpoint=None, seeds=(0, 1, 2, 3), readings: int = 3600, backend="openvino"):
    """{"seeds": {seed: {"live": figures, "offline_rest": figures}}, "mean": {...}}."""
    from beadsight.assets import shipped_model_path
    from beadsight.checkpoint import load_checkpoint
    from beadsight.errors import ConfigError

    path = checkpoint if checkpoint is not None else shipped_model_path()
    model = load_checkpoint(path)
    if not model.rest:
        raise ConfigError(f"{path}: not a rest-referenced model (it has no rest image to compare)")
    per_seed = {}
    for seed in seeds:
        live = read_live(model, seed, readings, backend)
        # the live pipeline reads nothing until its rest is taken: as many frames as it saw
        last_frame = int(round(live[-1, 0] * FPS)) + 1 if len(live) else readings
        offline = read_offline_rest(model, seed, last_frame, backend)
        per_seed[seed] = {"live": figures(live), "offline_rest": figures(offline)}
    mean = {
        row: {
            k: round(float(np.mean([s[row][k] for s in per_seed.values()])), 2)
            for k in FIGURES
            if all(s[row][k] is not None for s in per_seed.values())
        }
        for row in ("live", "offline_rest")
    }
    return {"seeds": per_seed, "mean": mean}


def main(argv: list[str] | None = None) -> None:
    from beadsight.inference.machine import cpu_summary

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default=None, help="checkpoint (default: the shipped sim model)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="simulator seeds")
    p.add_argument("--readings", type=int, default=3600, help="live readings per seed")
    p.add_argument("--backend", default="openvino", help="the runtime of both rows")
    p.add_argument("--json", action="store_true", help="print only the JSON object")
    args = p.parse_args(argv)
    if args.readings < 1:
        p.error(f"--readings must be >= 1, got {args.readings}")
    from beadsight.errors import BeadSightError

    start = time.perf_counter()
    try:
        result = compare(args.checkpoint, args.seeds, args.readings, args.backend)
    except BeadSightError as error:  # a missing or foreign checkpoint, an unknown backend
        p.error(str(error))
    wall = time.perf_counter() - start
    if not args.json:
        print(cpu_summary())
        print(f"{'seed':>5} {'row':<13}" + "".join(f" {k:>11}" for k in FIGURES.values()))
        rows = [(s, r, f) for s, v in result["seeds"].items() for r, f in v.items()]
        rows += [("mean", r, f) for r, f in result["mean"].items()]
        for seed, row, f in rows:
            print(f"{seed!s:>5} {row:<13}" + "".join(f" {f.get(k)!s:>11}" for k in FIGURES))
    checkpoint = str(args.checkpoint or "shipped sim model")
    out = {"checkpoint": checkpoint, "backend": args.backend, "cpu": cpu_summary(), **result}
    print(json.dumps({**out, "wall_s": round(wall, 1)}))


if __name__ == "__main__":
    main()
