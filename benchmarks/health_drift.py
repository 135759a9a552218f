"""Health on the simulator: when each drift is detected, and no alarm without drift.

    PYTHONPATH=src .venv/bin/python benchmarks/health_drift.py [--seconds 60]
        [--clean-minutes 10] [--seeds 5] [--checkpoint C] [--json]

Drift is the change of the rest state between two unloaded moments
(beadsight.health.monitor). Three parts:

* at rest: the simulated pouch rests (the finger stays above it) under each drift kind at
  its defaults (beadsight.sim.drift: settle 1.2 mm at the edge with a 20 s time constant;
  light -40 % brightness, +-20 % red/blue over 30 s; bump 1 mm at 5 s; a 2 mm bump):
  the simulated time each health state first shows;
* with presses: the same drifts while the simulator presses (a new bead packing after
  every press), read by a perfect model (each reading is the true force);
* with ``--checkpoint``: the drifts with presses again, read by the live pipeline
  (LiveSensor, default settings, every frame read, frames as fast as it reads them, so a
  rest reference is taken whenever one is ready: every 20 frames at rest);
* clean: ``--clean-minutes`` of the simulator's presses without drift on ``--seeds`` seeds,
  read by a perfect model and, with ``--checkpoint``, by the live pipeline: readings in a
  drifting or recalibrate state.

Frames at the checkpoint's size (64 px without one), 30 fps. The last line is a JSON
object (--json: the only line).
"""

from __future__ import annotations

import argparse
import json
import time

from beadsight.health.checkup import drift_timeline

STATES = ("ok", "drifting", "recalibrate")
KINDS = ("none", "settle", "light", "bump", "bump,bump_mm=2")
WARNINGS = ("drifting", "recalibrate")


def timeline(kind: str, seconds: float, presses: bool, size: int, seed: int = 0) -> dict:
    first = drift_timeline(
        None if kind == "none" else kind, seconds, image_size=size, seed=seed, presses=presses
    )
    return {s: round(first[s], 2) if s in first else None for s in STATES}


def live_run(checkpoint: str, minutes: float, seed: int, drift: str | None = None) -> dict:
    """The live pipeline on ``minutes`` of the simulator's presses under ``drift``."""
    from beadsight.checkpoint import load_checkpoint
    from beadsight.devices.virtual.camera import SimCamera
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    model = load_checkpoint(checkpoint)
    frames = int(minutes * 60 * 30)
    camera = SimCamera(model.image_size, seed=seed, drift=drift, realtime=False, queue_frames=1)
    sensor = LiveSensor(model, camera, LiveSettings(max_readings=frames)).open()
    # frames come as fast as they are read, stamped with the host's clock: take a rest
    # whenever the tracker has one (every 20 frames at rest, 0.67 s of simulated time)
    # rather than once a host second (fewer per simulated second, the faster the machine)
    sensor.watch.tracker.refresh_s = 0.0
    rests = []
    take = sensor.watch.on_rest
    sensor.watch.on_rest = lambda r: (rests.append(r.taken_at_s), take(r))
    counts, first = dict.fromkeys(("unknown", *STATES), 0), {}
    stream = sensor.updates(maxsize=1_000_000)
    with sensor:
        for u in stream:
            state = u.health.state
            counts[state] += 1
            first.setdefault(state, round(u.source_index / 30.0, 2))
    warned = sum(counts[s] for s in WARNINGS)
    return {
        "seed": seed,
        "readings": sum(counts.values()),
        "warning_readings": warned,
        "first": first,
        "rest_references": len(rests),
    }


def main() -> None:
    from beadsight.inference.machine import cpu_summary

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per drift")
    p.add_argument("--clean-minutes", type=float, default=10.0, help="clean run per seed, min")
    p.add_argument("--seeds", type=int, default=5, help="seeds of the clean runs")
    p.add_argument("--checkpoint", default=None, help="also run the clean runs live with it")
    p.add_argument("--json", action="store_true", help="print only the JSON object")
    args = p.parse_args()
    say = (lambda *a: None) if args.json else print
    size = 64
    if args.checkpoint:
        from beadsight.checkpoint import load_checkpoint

        size = load_checkpoint(args.checkpoint).image_size
    say(cpu_summary())
    out: dict = {"cpu": cpu_summary(), "image_size": size, "at_rest": {}, "with_presses": {}}
    for part, presses in (("at_rest", False), ("with_presses", True)):
        for kind in KINDS:
            start = time.perf_counter()
            out[part][kind] = timeline(kind, args.seconds, presses, size)
            wall = time.perf_counter() - start
            at = {
                s: f"{v:6.1f} s" if v is not None else "  never" for s, v in out[part][kind].items()
            }
            say(
                f"{part:12s} {kind:16s} ok at {at['ok']}, drifting at {at['drifting']}, "
                f"recalibrate at {at['recalibrate']} ({wall:.1f} s wall)"
            )
    if args.checkpoint:  # the drifts with presses, read by the live pipeline
        out["live_with_presses"] = {}
        for kind in KINDS[1:]:
            run = live_run(args.checkpoint, args.seconds / 60, 0, kind)
            out["live_with_presses"][kind] = run["first"]
            say(f"live         {kind:16s} {json.dumps(run)}")
    seconds = args.clean_minutes * 60
    out["clean"] = []
    for seed in range(args.seeds):
        start = time.perf_counter()
        perfect = timeline("none", seconds, True, size, seed)
        row = {"seed": seed, "perfect_model": perfect}
        if args.checkpoint:
            row["live"] = live_run(args.checkpoint, args.clean_minutes, seed)
        out["clean"].append(row)
        say(f"clean seed {seed}: {json.dumps(row)} ({time.perf_counter() - start:.0f} s wall)")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
