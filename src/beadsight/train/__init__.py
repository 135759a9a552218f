"""Training: configuration, the trainer (single process or DDP), run folders and windows.

* :mod:`~beadsight.train.config` - :class:`TrainConfig` and how it is resolved;
* :mod:`~beadsight.train.trainer` - :func:`train` and the training loop;
* :mod:`~beadsight.train.prepare` - split, windows and the model a run starts from;
* :mod:`~beadsight.train.step` - one optimizer step of the reference recipe;
* :mod:`~beadsight.train.distributed` - the DDP process group and the device;
* :mod:`~beadsight.train.run` - the run folder and its checkpoints;
* :mod:`~beadsight.train.windows`, :mod:`~beadsight.train.augment` - batches of windows.

Names that ``beadsight.train`` held before it became a package (``TrainConfig``,
``train``, ...) still resolve here, with a :class:`DeprecationWarning`, for one release.
"""

from __future__ import annotations

from typing import Any

# Where each name of the former ``beadsight.train`` module lives now.
_MOVED = {
    **dict.fromkeys(
        (
            "TrainConfig",
            "resolve_train_config",
            "PRECISIONS",
            "SIZE_MULTIPLE",
            "LR_SCHEDULES",
            "RESUME_FIXED_FIELDS",
            "INIT_MODEL_FIELDS",
            "INIT_SHAPE_FIELDS",
            "CONFIG_FILE",
        ),
        "config",
    ),
    **dict.fromkeys(("train", "MAX_LOG_INTERVAL_S"), "trainer"),
    **dict.fromkeys(("output_scale_kpa",), "prepare"),
    **dict.fromkeys(("model_inputs", "autocast", "optimizer_step"), "step"),
    **dict.fromkeys(
        (
            "RunFolder",
            "METRIC_KEYS",
            "SPLIT_FILE",
            "METRICS_FILE",
            "LAST_CHECKPOINT",
            "BEST_CHECKPOINT",
        ),
        "run",
    ),
}


def __getattr__(name: str) -> Any:
    module = _MOVED.get(name)
    if module is None:
        raise AttributeError(f"module 'beadsight.train' has no attribute {name!r}")
    import importlib

    from beadsight._compat import deprecated

    deprecated(f"beadsight.train.{name}", f"beadsight.train.{module}.{name}")
    return getattr(importlib.import_module(f"beadsight.train.{module}"), name)
