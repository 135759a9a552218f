"""``beadsight demo``: the shipped model on held-out simulated presses, as a report folder.

:func:`run_demo` simulates presses the model never saw (a seed of their own) at
the model's image size, runs the model over them, scores it with
:func:`beadsight.evaluation.evaluate.evaluate` (with the all-zero and mean-label
baselines), and writes a report folder:

* ``heldout.h5``: the simulated held-out presses (``--no-keep-data`` deletes it);
* ``metrics.json``, ``predictions.h5``, ``presses.csv`` (per press, worst first) and the
  evaluation plots (``examples.png``, ``force_scatter.png``, ``force_error.png``,
  ``force_traces.png``, ``region_error.png``; ``training_curve.png`` after ``--train``);
* ``animation.gif``: one press, camera frame | true map | predicted map;
* ``demo.json`` (what was run, seeds, timings) and ``index.html`` (the report).

:func:`run_train_demo` (``beadsight demo --train``) first simulates a small
training set and trains a small model from scratch, then reports it the same
way, with the measured training rate and what a full run would take on this
machine.

Modules: :mod:`~beadsight.demo.config` (:class:`DemoConfig`), :mod:`~beadsight.demo.run`
(running), :mod:`~beadsight.demo.report` (the report folder). Their names are importable
from here too, loaded on first use (so reading ``DemoConfig`` loads no torch).

The shipped model is ``beadsight/assets/sim_model.pt`` (see ``sim_model.md``
beside it), found with :mod:`importlib.resources`.
"""

from __future__ import annotations

import importlib
from typing import Any

_MODULES = ("config", "run", "report")


def __getattr__(name: str) -> Any:
    for module in _MODULES:
        loaded = importlib.import_module(f"beadsight.demo.{module}")
        if name in vars(loaded) and not name.startswith("_"):
            return getattr(loaded, name)
    raise AttributeError(f"module 'beadsight.demo' has no attribute {name!r}")
