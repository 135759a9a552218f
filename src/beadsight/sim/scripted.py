"""Scripted simulated sessions: a press held still for a long time (a steady load).

A steady load is what naive drift filters erase: an object resting in a gripper. The
:func:`steady_press` session rests for ``rest_s`` (the rest reference can be taken), then
presses at one place and holds the finger still for ``hold_s`` (the press's own dwell,
:attr:`~beadsight.sim.press.Press.dwell_s`), then rises. ``SimulatedSession(profile=
"mixed")`` draws such holds (and ramps and depth changes) for training sets. Used by the steady-load test and
``benchmarks/steady_press.py``.
"""

from __future__ import annotations

import dataclasses

from beadsight.errors import ConfigError
from beadsight.sim.config import SimConfig
from beadsight.sim.press import MM_MIN_PER_MM_S, Press

DEFAULT_HOLD_S = 60.0  # the steady-load target: a press held this long
DEFAULT_REST_S = 5.0  # unloaded, still frames before the press (the reference is taken)
DEFAULT_DEPTH_MM = 1.2  # below the pouch surface (about 3-5 N on the default pouch)


def steady_press(
    hold_s: float = DEFAULT_HOLD_S,
    *,
    xy_mm: tuple[float, float] = (0.0, 0.0),
    depth_mm: float = DEFAULT_DEPTH_MM,
    rest_s: float = DEFAULT_REST_S,
    ramp_feed_mm_min: float | None = None,
    config: SimConfig | None = None,
) -> tuple[SimConfig, list[Press]]:
    """The config and presses of a session that rests, then holds one press still.

    hold_s: how long the finger stays down (s); xy_mm: where (mm from the sensor centre);
    depth_mm: how deep below the pouch surface (mm); rest_s: unloaded time before
    the finger touches (s); ramp_feed_mm_min: the feed of a slow loading ramp into the
    pouch (:attr:`~beadsight.sim.press.Press.ramp_feed_mm_min`; None: the config's
    descend feed), a load that grows slowly. Pass both to
    :class:`~beadsight.devices.virtual.SimCamera` (``config=``, ``presses=``) or
    :class:`~beadsight.sim.session.SimulatedSession`. The config is ``config`` with a
    higher clear Z (for ``rest_s``); the press dwells ``hold_s``.
    """
    base = config if config is not None else SimConfig()
    for name, value in (("hold_s", hold_s), ("depth_mm", depth_mm), ("rest_s", rest_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ConfigError(f"steady_press: {name} must be a number > 0, got {value!r}")
    # the finger starts rest_s of descent above the pouch (the camera sees no finger there)
    clear_z_mm = base.surface_z_mm + rest_s * base.descend_feed_mm_min / MM_MIN_PER_MM_S
    cfg = dataclasses.replace(base, clear_z_mm=float(clear_z_mm))
    x, y = (float(v) for v in xy_mm)
    z_mm = float(base.surface_z_mm - depth_mm)
    return cfg, [Press(x, y, z_mm, dwell_s=float(hold_s), ramp_feed_mm_min=ramp_feed_mm_min)]
