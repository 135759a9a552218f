"""Live sensing: the sensor loop, frame sources, the TCP stream, the web viewer,
recorders (HDF5 readings, MCAP) and the live benchmark.

The sensor loop is :mod:`beadsight.live.sensor` (its settings in
:mod:`~beadsight.live.settings`, what it produces in :mod:`~beadsight.live.listeners`,
rates in :mod:`~beadsight.live.stats`, recording in :mod:`~beadsight.live.recorder`);
:mod:`beadsight.live.run` runs it for the command line. Names that ``beadsight.live``
held before it became a package (``LiveSensor``, ``run_live``, ...) still resolve
here, with a :class:`DeprecationWarning`, for one release.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    import importlib
    import importlib.util

    if importlib.util.find_spec(f"{__name__}.{name}") is not None:
        # `from beadsight.live import ros_messages` asks for an attribute first: a submodule
        # is imported as such (searching sensor and run would import torch)
        return importlib.import_module(f"{__name__}.{name}")
    from beadsight._compat import deprecated

    for module_name in ("beadsight.live.sensor", "beadsight.live.run"):
        module = importlib.import_module(module_name)
        if hasattr(module, name):
            deprecated(f"beadsight.live.{name}", f"{module_name}.{name}")
            return getattr(module, name)
    raise AttributeError(f"module 'beadsight.live' has no attribute {name!r}")
