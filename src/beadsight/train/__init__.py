"""Training: configuration, the trainer (single process or DDP), run folders and windows.

Names that ``beadsight.train`` held before it became a package (``TrainConfig``,
``train``, ...) still resolve here, with a :class:`DeprecationWarning`, for one release.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    import importlib

    from beadsight._compat import deprecated

    trainer = importlib.import_module("beadsight.train.trainer")
    if not hasattr(trainer, name):
        raise AttributeError(f"module 'beadsight.train' has no attribute {name!r}")
    deprecated(f"beadsight.train.{name}", f"beadsight.train.trainer.{name}")
    return getattr(trainer, name)
