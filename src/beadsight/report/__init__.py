"""Reports: the one HTML page builder and what goes on it.

:mod:`~beadsight.report.page` (a :class:`~beadsight.report.page.Report` and its
self-contained page, ``page.html`` beside it; the page of an evaluation's metrics),
:mod:`~beadsight.report.paper` (the paper's figures and the tables that compare with them),
:mod:`~beadsight.report.plots` (the figures) and :mod:`~beadsight.report.animation`
(camera | true map | predicted map of one press). ``evaluate``, ``demo`` and ``calibrate``
write their pages with it.
"""
