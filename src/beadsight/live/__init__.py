"""Live sensing: the sensor loop, frame sources, the TCP stream, the web viewer,
recorders (HDF5 readings, MCAP) and the live benchmark.

The sensor loop is :mod:`beadsight.live.sensor`. Names that ``beadsight.live`` held
before it became a package (``LiveSensor``, ``run_live``, ...) still resolve here, with
a :class:`DeprecationWarning`, for one release.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    import importlib

    from beadsight._compat import deprecated

    sensor = importlib.import_module("beadsight.live.sensor")
    if not hasattr(sensor, name):
        raise AttributeError(f"module 'beadsight.live' has no attribute {name!r}")
    deprecated(f"beadsight.live.{name}", f"beadsight.live.sensor.{name}")
    return getattr(sensor, name)
