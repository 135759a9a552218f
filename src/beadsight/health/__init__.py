"""Sensor health: the rest reference of the unloaded pouch, stillness, and drift.

:mod:`~beadsight.health.rest` (the rest reference and its file),
:mod:`~beadsight.health.stillness` (are the frames still?),
:mod:`~beadsight.health.flow` (bead motion between two rest states),
:mod:`~beadsight.health.monitor` (drift figures and states),
:mod:`~beadsight.health.watch` (what the sensing loop runs per reading) and
:mod:`~beadsight.health.checkup` (``beadsight health``).
"""
