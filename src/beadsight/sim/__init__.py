"""A physically motivated simulator of the BeadSight sensor and its calibration rig.

* :class:`SimConfig` - every parameter (presets for 75, 100 and 125 beads);
* :class:`PouchSimulator` - bead mechanics under a flat finger, true force, and the
  camera's sensor-space (``render``) and raw fisheye (``render_raw``) frames;
* :class:`SimulatedScale` - the HX711 kitchen scale the rig reads forces from;
* :class:`SimulatedSession` - the reference press pattern, frame by frame;
* :func:`simulate_dataset` - record a session as a dataset (scale force, commanded XY).

See ``docs/simulator.md``.
"""

from beadsight.sim.config import PRESET_BEAD_COUNTS, SimConfig
from beadsight.sim.dataset import SimulationError, sim_config_for, simulate_dataset
from beadsight.sim.press import Press, PressCycle, sample_presses
from beadsight.sim.scale import SimulatedScale
from beadsight.sim.session import SimFrame, SimulatedSession
from beadsight.sim.simulator import PouchSimulator

__all__ = [
    "PRESET_BEAD_COUNTS",
    "PouchSimulator",
    "Press",
    "PressCycle",
    "SimConfig",
    "SimFrame",
    "SimulatedScale",
    "SimulatedSession",
    "SimulationError",
    "sample_presses",
    "sim_config_for",
    "simulate_dataset",
]
