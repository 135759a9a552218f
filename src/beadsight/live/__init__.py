"""Live sensing: the sensor loop and its command-line run.

The sensor loop is :mod:`beadsight.live.sensor` (its settings in
:mod:`~beadsight.live.settings`, what it produces in :mod:`~beadsight.live.listeners`,
rates in :mod:`~beadsight.live.stats`); :mod:`beadsight.live.run` runs it for the
command line with one :class:`~beadsight.live.config.LiveRunConfig`. Its outputs live in
:mod:`beadsight.live.outputs` (viewer, ROS 2, Foxglove), its recordings in
:mod:`beadsight.live.recording` (HDF5, MCAP), the ROS 2 messages both use in
:mod:`beadsight.live.ros`.
"""
