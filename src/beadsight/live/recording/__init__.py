"""Recordings of live readings: the rules every recording follows and its writing thread
(:mod:`~beadsight.live.recording.recorder`), HDF5 readings files
(:mod:`~beadsight.live.recording.readings`) and MCAP with ROS 2 types
(:mod:`~beadsight.live.recording.mcap`)."""
