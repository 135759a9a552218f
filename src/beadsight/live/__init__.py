"""Live sensing: the sensor loop, frame sources, the TCP stream, the web viewer,
recorders (HDF5 readings, MCAP) and the live benchmark.

The sensor loop is :mod:`beadsight.live.sensor` (its settings in
:mod:`~beadsight.live.settings`, what it produces in :mod:`~beadsight.live.listeners`,
rates in :mod:`~beadsight.live.stats`, recording in :mod:`~beadsight.live.recorder`);
:mod:`beadsight.live.run` runs it for the command line.
"""
