"""``beadsight calibrate``: fit a base model to a new pouch from a few of its presses.

A workflow like :mod:`beadsight.demo`: :mod:`~beadsight.calibrate.config`
(:class:`~beadsight.calibrate.config.CalibrateConfig`, light, read by the command line),
:mod:`~beadsight.calibrate.run` (the stages), :mod:`~beadsight.calibrate.align` (what
adapts without training: the zero-press alignment and the force gain) and
:mod:`~beadsight.calibrate.report` (``metrics.json``, the learning curve, ``report.html``).
See docs/calibration.md.
"""
