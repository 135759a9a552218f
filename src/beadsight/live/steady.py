"""The steady-load check: a press held still in the simulator, read by a live sensor.

:func:`run_steady_press` runs :class:`~beadsight.live.sensor.LiveSensor` on
:func:`beadsight.sim.scripted.steady_press` (played as fast as the sensor reads, every
frame used) and compares the published force with the simulator's true force while the
finger is held still. Used by the steady-load test and ``benchmarks/steady_press.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SETTLE_S = 1.0  # the hold is judged from this long after the finger stops
RISE_S = 0.5  # ... to this long before the finger rises (the loaded frames' end)
HELD_FRACTION = 0.5  # frames whose true force is above this fraction of its peak are held


@dataclass(frozen=True)
class SteadyPressResult:
    """Forces while the press is held (``seconds`` of it), N; deviations in %."""

    seconds: float
    true_mean_n: float
    published_mean_n: float
    published_first_n: float
    published_last_n: float
    spread_pct: float  # (max - min) / mean of the published force over the held frames
    max_deviation_pct: float  # largest |published - true| / true over the held frames
    end_deviation_pct: float  # the same for the last held second
    health: str  # the health state at the end of the hold

    def summary(self) -> str:
        return (
            f"{self.seconds:.1f} s held: true {self.true_mean_n:.3f} N, published "
            f"{self.published_first_n:.3f} -> {self.published_last_n:.3f} N (mean "
            f"{self.published_mean_n:.3f}, spread {self.spread_pct:.1f} %), max deviation {self.max_deviation_pct:.1f} %, "
            f"at the end {self.end_deviation_pct:.1f} %, health {self.health}"
        )


def run_steady_press(
    checkpoint: str | Path | Any = None,
    hold_s: float = 60.0,
    *,
    drift: str | None = None,
    settings: Any = None,
    seed: int = 0,
) -> SteadyPressResult:
    """Hold a simulated press ``hold_s`` s and read it live (module docstring).

    drift: the simulator's drift text; settings: base
    :class:`~beadsight.live.settings.LiveSettings`.
    """
    from beadsight.checkpoint import load_checkpoint, shipped_model_path
    from beadsight.devices.virtual.camera import SimCamera
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings
    from beadsight.sim.scripted import steady_press

    model = load_checkpoint(checkpoint if checkpoint is not None else shipped_model_path())
    config, presses = steady_press(hold_s)
    camera = SimCamera(
        model.image_size,
        config=config,
        presses=presses,
        drift=drift,
        seed=seed,
        realtime=False,
        queue_frames=1,  # one frame at a time: a reading for every frame, as at 30 Hz
    )
    settings = settings or LiveSettings()
    sensor = LiveSensor(model, camera, settings).open()
    rows = []
    stream = sensor.updates(maxsize=1_000_000)
    with sensor:
        for u in stream:
            health = u.health.state if u.health is not None else "none"
            rows.append(
                (u.source_index / config.fps, u.reading.force_n, u.reference_force_n, health)
            )
    return _judge(rows)


def _judge(rows: list[tuple[float, float, float, str]]) -> SteadyPressResult:
    t = np.array([r[0] for r in rows])
    published = np.array([r[1] for r in rows])
    true = np.array([r[2] for r in rows])
    loaded = true > HELD_FRACTION * true.max()
    start, end = t[loaded][0] + SETTLE_S, t[loaded][-1] - RISE_S
    held = loaded & (t >= start) & (t <= end)
    if not held.any():
        raise ValueError("the press was not held long enough to judge")
    deviation = np.abs(published[held] - true[held]) / true[held] * 100
    last = held & (t >= t[held][-1] - 1.0)
    end_dev = np.abs(published[last] - true[last]) / true[last] * 100
    return SteadyPressResult(
        seconds=float(t[held][-1] - t[held][0]),
        true_mean_n=float(true[held].mean()),
        published_mean_n=float(published[held].mean()),
        published_first_n=float(published[held][0]),
        published_last_n=float(published[held][-1]),
        spread_pct=float(np.ptp(published[held]) / max(abs(published[held].mean()), 1e-9) * 100),
        max_deviation_pct=float(deviation.max()),
        end_deviation_pct=float(end_dev.max()),
        health=rows[int(np.flatnonzero(held)[-1])][3],
    )
