"""Scoring a model: the paper's metrics, evaluation on a dataset, prediction over a
recording or video, and the plots of a report."""
