"""Virtual twins of the rig's devices, speaking the real protocols on pseudo-terminals.

* :class:`VirtualPrinter` - Marlin G-code with motion in simulated time.
* :class:`VirtualScale` - the HX711 scale (beadsight firmware or reference sketch).
* :class:`VirtualCamera` - frames from a render function, OpenCVCamera's interface.
* :class:`VirtualRig` - all three driven by one simulated pouch (``beadsight.sim``).
* :class:`SimClock` - simulated time, optionally faster than real time.

Linux/macOS only (they use ``pty``).
"""

from beadsight.devices.virtual.camera import VirtualCamera
from beadsight.devices.virtual.clock import SimClock
from beadsight.devices.virtual.printer import VirtualPrinter
from beadsight.devices.virtual.rig import VirtualRig
from beadsight.devices.virtual.scale import VirtualScale

__all__ = ["SimClock", "VirtualCamera", "VirtualPrinter", "VirtualRig", "VirtualScale"]
