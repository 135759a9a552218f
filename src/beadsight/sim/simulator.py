"""``PouchSimulator``: one simulated BeadSight sensor (mechanics + camera).

Drive it with the finger's position and depth, read back the true force, and
render what the camera sees::

    sim = PouchSimulator(SimConfig(), seed=0)
    force_n = sim.step(1 / 30, finger_xy_mm=(3.0, -5.0), finger_depth_mm=1.2)
    frame = sim.render()       # (256, 256, 3) uint8 RGB, sensor space
    raw = sim.render_raw()     # (1024, 1280, 3) uint8 BGR, fisheye camera frame

Seeded and deterministic: the same seed and the same sequence of calls give the
same forces and frames. Mechanics, the pouch's static appearance, sensor-space
rendering and raw rendering draw from separate random streams, so rendering (at
any size, or not at all) never changes the mechanics.
"""

from __future__ import annotations

import numpy as np

from beadsight.sim.config import SimConfig
from beadsight.sim.optics.render import SensorRenderer
from beadsight.sim.pouch import BeadPouch, PouchView

_STREAMS = 4  # mechanics, appearance, sensor-space frame noise, raw frame noise


class PouchSimulator:
    """A pouch of beads under a flat finger, seen by the sensor's camera.

    config: the simulated sensor (:class:`SimConfig`); seed: int or SeedSequence.
    """

    def __init__(self, config: SimConfig | None = None, seed: int | np.random.SeedSequence = 0):
        self.config = config if config is not None else SimConfig()
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        mech, self._appearance, self._frame_seq, self._raw_seq = seq.spawn(_STREAMS)
        self.pouch = BeadPouch(self.config, np.random.default_rng(mech))
        self._renderer: SensorRenderer | None = None
        self._raw_renderer: SensorRenderer | None = None
        self._raw_camera = None

    # --- mechanics ----------------------------------------------------------------------
    def step(self, dt_s: float, finger_xy_mm, finger_depth_mm: float) -> float:
        """Advance ``dt_s`` s. finger_xy_mm: (2,) mm from the sensor centre (printer
        frame); finger_depth_mm: depth below the pouch surface (<= 0: not touching).
        Returns the true normal force on the finger, N (>= 0)."""
        return self.pouch.step(dt_s, finger_xy_mm, finger_depth_mm)

    @property
    def time_s(self) -> float:
        """Simulated time since construction, s."""
        return self.pouch.time_s

    @property
    def force_n(self) -> float:
        """True normal force after the last step, N."""
        return self.pouch.force_n

    @property
    def in_contact(self) -> bool:
        return self.pouch.in_contact

    @property
    def bead_positions_mm(self) -> np.ndarray:
        """(n_beads, 2) float64 lagged bead centres (no jitter), mm from the sensor centre."""
        return self.pouch.pos[~self.pouch.is_bubble].copy()

    @property
    def bead_rest_positions_mm(self) -> np.ndarray:
        """(n_beads, 2) float64 current resting places (the arrangement), mm."""
        return self.pouch.home[~self.pouch.is_bubble].copy()

    @property
    def bead_radii_mm(self) -> np.ndarray:
        """(n_beads,) float64 radii of the uncompressed beads, mm."""
        return self.pouch.radius_mm[~self.pouch.is_bubble].copy()

    def view(self) -> PouchView:
        return self.pouch.view()

    # --- camera ---------------------------------------------------------------------------
    def render(self) -> np.ndarray:
        """Sensor-space frame: (S, S, 3) uint8 RGB, S = ``config.image_size_px``."""
        if self._renderer is None:
            self._renderer = SensorRenderer(
                self.config,
                self.config.image_size_px,
                self._appearance,
                np.random.default_rng(self._frame_seq),
                jpeg_quality=self.config.jpeg_quality,
            )
        return self._renderer.render(self.pouch.view())

    def render_raw(self) -> np.ndarray:
        """Raw camera frame: (1024, 1280, 3) uint8 BGR, fisheye, as a USB camera gives it.

        The reference preprocessing (:meth:`beadsight.preprocess.Preprocessor.reference`)
        maps it back to approximately :meth:`render`'s image.
        """
        if self._raw_camera is None:
            from beadsight.sim.optics.fisheye import RawCamera

            rng = np.random.default_rng(self._raw_seq)
            self._raw_renderer = SensorRenderer(
                self.config, self.config.raw_render_px, self._appearance, rng, noise=False
            )
            self._raw_camera = RawCamera(self.config, self.config.raw_render_px, rng)
        assert self._raw_renderer is not None
        sensor = self._raw_renderer.render(self.pouch.view())
        return self._raw_camera.render(sensor)
