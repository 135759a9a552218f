"""The virtual rig: printer, scale and camera driven by one simulated pouch.

:class:`VirtualRig` owns a :class:`~beadsight.sim.simulator.PouchSimulator` and a world
thread that, every few milliseconds, moves the simulated finger along the virtual
printer's motion (finger XY = printer XY - ``SimConfig.centre_xy_mm``; depth =
``SimConfig.surface_z_mm`` - printer Z), steps the pouch and hands the true force to the
virtual scale. The virtual camera renders the same pouch, so position, force and frames
agree. The printer and scale sit on pseudo-terminals and are driven through the real
drivers; the camera is a :class:`~beadsight.devices.virtual.camera.VirtualCamera`, a
:class:`~beadsight.devices.Camera` like the USB one (collection and live sensing read it).

Example::

    with VirtualRig(seed=0) as rig:
        with rig.make_printer() as printer, rig.make_scale() as scale, rig.camera as camera:
            printer.home()
            printer.move(151.8, 108.9, 137.5, 700)
            printer.move(None, None, 128.0, 200)
            printer.wait_for_motion()
            print(scale.wait_for_reading().grams, camera.read_latest().image.shape)

Command line: ``beadsight collect --virtual ...`` builds one of these.

Faults are injected on the parts: ``rig.printer_device`` (:class:`VirtualPrinter`),
``rig.scale_device`` (:class:`VirtualScale`), ``rig.camera`` (:class:`VirtualCamera`).
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from beadsight.devices.clock import SimClock
from beadsight.devices.envelope import SafetyEnvelope
from beadsight.devices.hx711 import HX711Scale
from beadsight.devices.marlin import MarlinPrinter
from beadsight.devices.reader import ReaderThread
from beadsight.devices.virtual.camera import VirtualCamera
from beadsight.devices.virtual.printer import VirtualPrinter
from beadsight.devices.virtual.scale import VirtualScale

logger = logging.getLogger(__name__)

WORLD_PERIOD_S = 0.01  # host seconds between world updates
WORLD_STEP_S = 0.01  # longest simulated step of the pouch mechanics
MAX_SUBSTEPS = 20  # per update; after a long host stall the steps get longer instead
HOME_ABOVE_CLEAR_MM = 40.0  # G28 parks the finger this far above the clear height
ENVELOPE_DEPTH_MM = 3.0  # the envelope's floor lies this far below the pouch surface
ENVELOPE_CLEARANCE_MM = 5.0  # ... and its clear height this far above it
CAMERA_MODES = ("raw", "sensor")


class VirtualRig:
    """One simulated world with a virtual printer, scale and camera. A context manager.

    sim_config: the simulated sensor and rig (default ``SimConfig()``); seed: the
    simulator's seed. time_scale: simulated seconds per host second (1 = real time).
    scale_protocol: "beadsight" or "reference"; scale_rate_hz: default
    ``sim_config.scale_rate_hz``; scale_noise_g: default ``sim_config.scale_noise_g``.
    camera_mode: "raw" = (1024, 1280, 3) BGR fisheye frames as the USB camera gives
    (``PouchSimulator.render_raw``, slow: ~70 ms a frame), "sensor" = (S, S, 3) BGR
    sensor-space frames (``render``, fast; preprocess with ``Preprocessor.identity``).
    camera_fps: default ``sim_config.fps``. world_step_s: longest mechanics step.
    """

    def __init__(
        self,
        sim_config=None,
        seed: int = 0,
        *,
        time_scale: float = 1.0,
        scale_protocol: str = "beadsight",
        scale_rate_hz: float | None = None,
        scale_noise_g: float | None = None,
        camera_mode: str = "raw",
        camera_fps: float | None = None,
        world_step_s: float = WORLD_STEP_S,
        printer_banner: bool = True,
    ):
        from beadsight.sim.config import SimConfig
        from beadsight.sim.simulator import PouchSimulator

        if camera_mode not in CAMERA_MODES:
            raise ValueError(f"camera_mode must be one of {CAMERA_MODES}, got {camera_mode!r}")
        if not world_step_s > 0:
            raise ValueError(f"world_step_s must be > 0, got {world_step_s}")
        self.config = sim_config if sim_config is not None else SimConfig()
        self.seed = seed
        self.camera_mode = camera_mode
        self.world_step_s = float(world_step_s)
        self.clock = SimClock(time_scale)
        self.simulator = PouchSimulator(self.config, seed)
        self.envelope = SafetyEnvelope.around_sensor(
            self.config.centre_xy_mm,
            self.config.surface_z_mm,
            max_depth_mm=ENVELOPE_DEPTH_MM,
            clearance_mm=ENVELOPE_CLEARANCE_MM,
            xy_half_range_mm=self.config.press_range_mm + 1.0,
        )
        self.force_n = 0.0  # true force on the finger after the last world step, N
        self.finger_position_mm = (0.0, 0.0, 0.0)  # printer coordinates at the last step
        self._world_lock = threading.RLock()
        self._t = 0.0
        self._world: ReaderThread | None = None
        home = (0.0, 0.0, self.config.clear_z_mm + HOME_ABOVE_CLEAR_MM)
        self.printer_device = VirtualPrinter(
            clock=self.clock, home_position_mm=home, banner=printer_banner, seed=seed
        )
        self.scale_device = VirtualScale(
            protocol=scale_protocol,
            clock=self.clock,
            rate_hz=scale_rate_hz if scale_rate_hz is not None else self.config.scale_rate_hz,
            noise_g=scale_noise_g if scale_noise_g is not None else self.config.scale_noise_g,
            force_fn=self._force_at,
            seed=seed,
        )
        size = (1280, 1024) if camera_mode == "raw" else (self.config.image_size_px,) * 2
        self.camera = VirtualCamera(
            self._render,
            width=size[0],
            height=size[1],
            fps=camera_fps if camera_fps is not None else self.config.fps,
            clock=self.clock,
        )

    # --- lifecycle --------------------------------------------------------------------
    def start(self) -> VirtualRig:
        """Start the devices and the world thread."""
        if self._world is None:
            self.finger_position_mm = self.printer_device.current_position()
            self._t = self.clock.now()
            self.printer_device.start()
            self.scale_device.start()
            self._world = ReaderThread("virtual rig world", self._world_loop).start()
        return self

    def close(self) -> None:
        """Stop everything: camera reader, world thread, pty devices (ports vanish)."""
        self.camera.close()
        world, self._world = self._world, None
        if world is not None:
            world.stop()
        self.printer_device.close()
        self.scale_device.close()

    def __enter__(self) -> VirtualRig:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- ports and drivers --------------------------------------------------------------
    @property
    def printer_port(self) -> str:
        """The virtual printer's serial port (``/dev/pts/N``)."""
        return self.printer_device.port

    @property
    def scale_port(self) -> str:
        """The virtual scale's serial port (``/dev/pts/N``)."""
        return self.scale_device.port

    def make_printer(self, **kwargs) -> MarlinPrinter:
        """A (not yet connected) MarlinPrinter on the virtual port with the rig's envelope."""
        kwargs.setdefault("envelope", self.envelope)
        return MarlinPrinter(self.printer_port, **kwargs)

    def make_scale(self, **kwargs) -> HX711Scale:
        """A (not yet connected) HX711Scale on the virtual port."""
        return HX711Scale(self.scale_port, **kwargs)

    # --- world ----------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        """Simulated time the world has reached, s."""
        return self._t

    def depth_mm(self) -> float:
        """Finger depth below the pouch surface at the last world step (<= 0: not touching)."""
        return self.config.surface_z_mm - self.finger_position_mm[2]

    def advance_to(self, t_sim: float) -> None:
        """Step the pouch up to simulated time ``t_sim`` along the printer's motion."""
        with self._world_lock:
            remaining = t_sim - self._t
            if remaining <= 0:
                return
            steps = min(MAX_SUBSTEPS, max(1, int(np.ceil(remaining / self.world_step_s - 1e-9))))
            dt = remaining / steps
            cx, cy = self.config.centre_xy_mm
            for _ in range(steps):
                t_next = self._t + dt
                x, y, z = self.printer_device.position_at(t_next)
                depth = self.config.surface_z_mm - z
                self.force_n = float(self.simulator.step(dt, (x - cx, y - cy), depth))
                self.finger_position_mm = (x, y, z)
                self._t = t_next

    def _world_loop(self, stop: threading.Event) -> None:
        try:
            while not stop.wait(WORLD_PERIOD_S):
                self.advance_to(self.clock.now())
        except Exception:  # noqa: BLE001 - the world thread must say why it died
            logger.exception("virtual rig world thread crashed")

    def _force_at(self, t_sim: float) -> float:
        """The scale's load at ``t_sim`` (N): the world's latest force (zero-order hold)."""
        return self.force_n

    def _render(self) -> np.ndarray:
        """A camera frame of the pouch now: (H, W, 3) uint8 BGR."""
        self.advance_to(self.clock.now())
        with self._world_lock:
            if self.camera_mode == "raw":
                return self.simulator.render_raw()
            return np.ascontiguousarray(self.simulator.render()[..., ::-1])
