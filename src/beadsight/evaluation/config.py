"""Defaults of :func:`~beadsight.evaluation.evaluate.evaluate` and
:func:`~beadsight.evaluation.predict.predict_recording`, in one light module (no torch)
that both functions and the command line read."""

from __future__ import annotations

SPLIT_CHOICES = ("test", "val", "all")  # presses evaluate scores
DEFAULT_SPLIT = "test"
DEFAULT_DEVICE = "auto"  # auto | cpu | cuda | cuda:N | mps
EVALUATE_BATCH_SIZE = 16  # windows per forward pass
PREDICT_BATCH_SIZE = 8
PREDICT_PREPROCESS = "auto"  # auto | none | reference | reference-linear | lens .json
