"""From a recording to a dataset: ``run`` (``beadsight process``: align, label, write),
``config`` (its settings), ``frame_labels`` (each frame's force and press), ``images``
(the frames' preprocessing) and ``qa`` (the quality figure). See ``docs/recording-format.md``."""
