"""Forged checkpoints: torch files whose pickle describes numpy arrays numpy would never write.

The pickle stream is what an attacker controls. ``ForgingPickler`` writes a
:class:`Forged` placeholder as the opcodes numpy itself uses for an array
(``_reconstruct`` + ``BUILD`` with ``(1, shape, dtype, fortran, raw bytes)``), but
with a dtype state chosen by the test (for example an object dtype whose flags were
cleared, so numpy takes raw bytes as object pointers). Only names a reference
checkpoint legitimately uses appear in the stream: ``numpy.core.multiarray._reconstruct``,
``numpy.ndarray``, ``numpy.dtype``, ``_codecs.encode``.
"""

from __future__ import annotations

import pickle
import types
from pathlib import Path
from typing import Any

import numpy as np
import torch

OBJECT_FLAGS = np.dtype("O").flags  # what numpy writes for an object dtype (refcount checks)


class ForgedDtype:
    """A dtype pickled as ``numpy.dtype(spec, False, True)`` with BUILD ``state``."""

    def __init__(self, spec: str, state: tuple):
        self.spec, self.state = spec, state


class Forged:
    """An array pickled as ``_reconstruct(ndarray, (0,), b'b')`` with BUILD state."""

    def __init__(self, shape: tuple[int, ...], dtype: ForgedDtype, raw: bytes, fortran=False):
        self.shape, self.dtype, self.raw, self.fortran = shape, dtype, raw, fortran


def dtype_state(order="|", names=None, fields=None, elsize=-1, alignment=-1, flags=0) -> tuple:
    """numpy's dtype ``__setstate__`` tuple (version 3)."""
    return (3, order, None, names, fields, elsize, alignment, flags)


def _reconstruct_function():
    core = getattr(np, "_core", None) or np.core
    return core.multiarray._reconstruct


class ForgingPickler(pickle.Pickler):
    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, Forged):
            state = (1, obj.shape, obj.dtype, obj.fortran, obj.raw)
            return (_reconstruct_function(), (np.ndarray, (0,), b"b"), state)
        if isinstance(obj, ForgedDtype):
            return (np.dtype, (obj.spec, False, True), obj.state)
        return NotImplemented


_FORGING_MODULE = types.ModuleType("forging_pickle")
_FORGING_MODULE.Pickler = ForgingPickler  # type: ignore[attr-defined]


def save_forged(obj: Any, path: Path) -> Path:
    """torch.save ``obj`` (a zip checkpoint), writing Forged/ForgedDtype as described."""
    torch.save(obj, path, pickle_module=_FORGING_MODULE)
    return path


def object_array_with_cleared_flags() -> Forged:
    """Three 'objects' whose pointers are the bytes 0x41...: numpy would dereference them."""
    return Forged((3,), ForgedDtype("O8", dtype_state(flags=0)), b"\x41" * 24)


def f8_with_object_field() -> Forged:
    """An f8 dtype whose state gives it one object field at offset 0 (flags cleared)."""
    obj = ForgedDtype("O8", dtype_state(flags=OBJECT_FLAGS))
    state = dtype_state("<", names=("x",), fields={"x": (obj, 0)}, elsize=8, alignment=8)
    return Forged((3,), ForgedDtype("f8", state), b"\x41" * 24)
