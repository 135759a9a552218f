"""Virtual twins of the rig's devices and of the sensor camera.

* :class:`VirtualPrinter` - Marlin G-code with motion in simulated time.
* :class:`VirtualScale` - the HX711 scale (beadsight firmware or reference sketch).
* :class:`VirtualCamera` - frames from a render function, the real cameras' interface;
  :class:`PlaybackCamera` plays given frames, :class:`SimCamera` the simulated sensor.
* :class:`VirtualRig` - printer, scale and camera driven by one simulated pouch
  (``beadsight.sim``).
* :class:`SimClock` - simulated time, optionally faster than real time;
  :class:`SteppedClock` - simulated time that moves only when a device waits;
  :class:`FrameClock` - capture stamps one frame period apart (a camera read as fast as it
  plays).

The printer, scale and rig are Linux/macOS only (they use ``pty``); the cameras run
anywhere. Names are imported on first use, so importing a camera does not need ``pty``.
"""

from __future__ import annotations

from beadsight.lazy import lazy_names

_WHERE = {
    "PlaybackCamera": "beadsight.devices.virtual.camera",
    "SimCamera": "beadsight.devices.virtual.camera",
    "VirtualCamera": "beadsight.devices.virtual.camera",
    "SimClock": "beadsight.devices.clock",
    "SteppedClock": "beadsight.devices.clock",
    "FrameClock": "beadsight.devices.clock",
    "VirtualPrinter": "beadsight.devices.virtual.printer",
    "VirtualRig": "beadsight.devices.virtual.rig",
    "VirtualScale": "beadsight.devices.virtual.scale",
}

__all__ = sorted(_WHERE)
__getattr__ = lazy_names(__name__, _WHERE)


def __dir__() -> list[str]:
    return __all__
