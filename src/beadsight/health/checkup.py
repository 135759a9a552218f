"""``beadsight health``: watch the sensor at rest for a while and say how it is.

:func:`run_checkup` runs a live sensor (:class:`~beadsight.live.sensor.LiveSensor`) for
``seconds`` (the pouch should be unloaded), then returns the newest
:class:`~beadsight.health.monitor.HealthReport` and, if asked, saves the newest rest
reference the sensor took as a rest file for later runs (``beadsight live --rest FILE``,
``beadsight calibrate --rest FILE``). :func:`drift_timeline` times the health states of
the simulated pouch at rest under a drift (``benchmarks/health_drift.py``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from beadsight.errors import BeadSightError
from beadsight.files import refuse_existing

POLL_S = 0.1  # how often the checkup looks at the sensor


def run_checkup(
    sensor: Any,
    seconds: float,
    *,
    save_rest: str | Path | None = None,
    overwrite: bool = False,
) -> Any:
    """Run ``sensor`` (a LiveSensor with health on, not started) ``seconds`` of host time;
    returns its health report. save_rest: write the newest rest reference there (.npz)."""
    if not seconds > 0:
        raise BeadSightError(f"--seconds must be > 0, got {seconds!r}")
    if save_rest is not None:
        refuse_existing(save_rest, overwrite)
    with sensor:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not sensor.wait(POLL_S):
            pass
        if sensor.error is not None:
            raise sensor.error
        report = sensor.watch.monitor.flush()
        reference = sensor.watch.rest
    if save_rest is not None:
        if reference is None or reference.origin == "file":
            raise BeadSightError(
                f"--save-rest {save_rest}: no rest reference yet (the pouch was not "
                f"unloaded and still for long enough in {seconds:g} s)"
            )
        reference.save(save_rest)
    return report


def drift_timeline(
    drift: str | None,
    seconds: float,
    *,
    image_size: int = 64,
    seed: int = 0,
    presses: bool = False,
) -> dict[str, float]:
    """Simulated time (s) at which each health state first shows under ``drift``
    (:func:`beadsight.sim.drift.parse_drift` text) over ``seconds`` of the simulator at
    ``image_size`` px, 30 fps, read by a perfect model (each reading is the simulator's
    true force). presses: False - the pouch rests (the finger stays above it); True - the
    simulator's endless random presses, a new packing after each."""
    import dataclasses

    import numpy as np

    from beadsight.health.watch import SensorWatch
    from beadsight.inference.predictor import PressureReading
    from beadsight.sim.config import SimConfig
    from beadsight.sim.drift import DriftRenderer, parse_drift
    from beadsight.sim.press import Press
    from beadsight.sim.session import SimulatedSession

    cfg = SimConfig(image_size_px=image_size)
    if not presses:  # one press that never comes down: the finger stays above the pouch
        cfg = dataclasses.replace(cfg, dwell_s=float(seconds))
    render = DriftRenderer(parse_drift(drift), image_size, cfg.sensor_size_mm)
    watch = SensorWatch(cfg.sensor_size_mm)
    empty = np.zeros((image_size, image_size), np.float32)
    first: dict[str, float] = {}
    script = None if presses else [Press(0.0, 0.0, cfg.clear_z_mm)]
    for record in SimulatedSession(cfg, seed, script):
        t = record.frame_index / cfg.fps
        if t > seconds:
            break
        force = float(record.true_force_n)
        truth = PressureReading(empty, force, np.full(2, np.nan), False, empty > 0, 0.0, t, 0, 0, 0)
        report = watch.process(render.apply(record.frame_rgb, t), truth)
        first.setdefault(report.state, t)
    watch.close()
    return first
