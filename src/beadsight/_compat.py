"""Old module paths, kept importable for one release with a :class:`DeprecationWarning`.

Version 0.2 moved modules into packages (``beadsight.predictor`` became
``beadsight.inference.predictor``, ...). A finder at the end of ``sys.meta_path``
answers only for the old names, which no longer exist as files, and hands out the
new module itself, so both names refer to one object.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

REMOVED_IN = "0.3"

MOVED_MODULES = {
    "beadsight.backends": "beadsight.inference.legacy_backends",
    "beadsight.export": "beadsight.inference.export",
    "beadsight.predictor": "beadsight.inference.predictor",
    "beadsight.live_sources": "beadsight.live.sources",
    "beadsight.stream": "beadsight.live.stream",
    "beadsight.viewer": "beadsight.live.viewer",
    "beadsight.viewer.server": "beadsight.live.viewer.server",
    "beadsight.readings": "beadsight.live.readings",
    "beadsight.rosbag": "beadsight.live.mcap",
    "beadsight.latency": "beadsight.live.bench",
    "beadsight.evaluate": "beadsight.evaluation.evaluate",
    "beadsight.predict": "beadsight.evaluation.predict",
    "beadsight.metrics": "beadsight.evaluation.metrics",
    "beadsight.plots": "beadsight.evaluation.plots",
    "beadsight.data.windows": "beadsight.train.windows",
    "beadsight.collect": "beadsight.rig.collect",
    "beadsight.devices.virtual.clock": "beadsight.devices.clock",
}


def deprecated(old: str, new: str, stacklevel: int = 3) -> None:
    warnings.warn(
        f"{old} is deprecated and goes away in beadsight {REMOVED_IN}; use {new}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def lazy_names(package: str, where: dict[str, str]):
    """A module ``__getattr__`` (PEP 562) for ``package`` that imports each name of
    ``where`` (name -> defining module) on first use, so the package imports light."""

    def __getattr__(name: str):
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    return __getattr__


def renamed_attribute(owner: str, old: str, new: str) -> property:
    """A read-only property ``old`` that warns and returns attribute ``new``."""

    def get(self):
        deprecated(f"{owner}.{old}", f"{owner}.{new}")
        return getattr(self, new)

    return property(get, doc=f"Deprecated: :attr:`{new}`.")


class MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old module name to the module that replaced it."""

    def find_spec(self, fullname, path=None, target=None):  # noqa: D102
        if fullname not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):  # noqa: D102
        return None  # a placeholder; exec_module swaps in the real module

    def exec_module(self, module) -> None:  # noqa: D102
        new = MOVED_MODULES[module.__name__]
        deprecated(module.__name__, new)
        # the import system returns whatever sys.modules holds under the name after this
        sys.modules[module.__name__] = importlib.import_module(new)


def install() -> None:
    if not any(isinstance(f, MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.append(MovedModuleFinder())
