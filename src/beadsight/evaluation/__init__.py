"""Scoring a model: the paper's metrics, evaluation on a dataset and prediction over a
recording or video. Their reports are drawn by :mod:`beadsight.report`."""
