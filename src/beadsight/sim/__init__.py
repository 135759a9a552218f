"""A physically motivated simulator of the BeadSight sensor and its calibration rig.

* :class:`SimConfig` - every parameter (presets for 75, 100 and 125 beads);
* :class:`PouchSimulator` - bead mechanics under a flat finger, true force, and the
  camera's sensor-space (``render``) and raw fisheye (``render_raw``) frames;
* :class:`SimulatedScale` - the HX711 kitchen scale the rig reads forces from;
* :class:`SimulatedSession` - the reference press pattern, or a profile of long holds,
  slow ramps and depth changes while held (:class:`Press`, ``PROFILES``), frame by frame;
* :func:`simulate_dataset` - record a session as a dataset (scale force, commanded XY);
* :func:`sample_pouch` / :class:`PouchDistribution` - the range of real builds (pouch,
  light, camera, image), with a held-out split, for base models;
* :data:`LOOK_SPLITS` / :func:`sample_look` - look families (beads, background, light,
  camera) as unlike each other as two renderers, two of them held out.

See ``docs/simulator.md``.
"""

from __future__ import annotations

from beadsight.lazy import lazy_names

# The names above, each loaded from its module on first use (so reading SimConfig does
# not load the simulator, scipy or h5py).
_NAMES = {
    "LOOK_SPLITS": "beadsight.sim.looks",
    "LookSample": "beadsight.sim.looks",
    "PRESET_BEAD_COUNTS": "beadsight.sim.config",
    "PROFILES": "beadsight.sim.press",
    "HoldMove": "beadsight.sim.press",
    "PouchDistribution": "beadsight.sim.variety",
    "PouchSample": "beadsight.sim.variety",
    "PouchSimulator": "beadsight.sim.simulator",
    "Press": "beadsight.sim.press",
    "PressCycle": "beadsight.sim.press",
    "SimConfig": "beadsight.sim.config",
    "SimFrame": "beadsight.sim.session",
    "SimulatedScale": "beadsight.sim.scale",
    "SimulatedSession": "beadsight.sim.session",
    "SimulationError": "beadsight.sim.dataset",
    "sample_look": "beadsight.sim.looks",
    "sample_pouch": "beadsight.sim.variety",
    "sample_presses": "beadsight.sim.press",
    "sim_config_for": "beadsight.sim.dataset",
    "simulate_dataset": "beadsight.sim.dataset",
}

__all__ = sorted(_NAMES)
__getattr__ = lazy_names(__name__, _NAMES)
