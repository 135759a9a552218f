"""numpy arrays from untrusted pickles, built only after their description is checked.

Reference checkpoints are pickled training dicts holding numpy arrays. Allowing
numpy's own unpickling functions (``_reconstruct``, ``dtype``, ``scalar``) is not
safe: a pickle can clear a dtype's flags through ``dtype.__setstate__`` so that an
object dtype (or an ``f8`` carrying object fields) no longer says it holds
pointers, and then fill the array with raw bytes that numpy later dereferences as
Python objects (a crash at best). So the names a pickle uses for them map to the
stand-ins below instead: they accept plain numeric and bool dtypes only (no
fields, no sub-arrays, no objects, no metadata), check that the raw bytes fill the
claimed shape exactly, and build a fresh array with ``np.frombuffer``.

Use::

    with torch.serialization.safe_globals(safe_globals()):
        obj = torch.load(path, weights_only=True)
    obj = materialize(obj)   # stand-ins -> numpy arrays; UnsafeContent if unfinished

Anything else raises :class:`UnsafeContent` with a sentence saying what was refused.

:func:`read_npz` reads named arrays of an ``.npz`` file the same way: each array's
declared dtype, shape and size (in the zip directory and in its ``.npy`` header) are
checked against what the caller expects before any of its data is read, and no more
bytes than the expected size are ever decompressed.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

# numpy type codes (kind + item size) that are plain numbers: nothing else is built
SAFE_TYPE_CODES = frozenset(
    ["b1", "i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "f2", "f4", "f8", "c8", "c16"]
)
MAX_NDIM = 32  # numpy's own limit on array dimensions
_BYTE_ORDERS = ("<", ">", "|", "=")


class UnsafeContent(Exception):
    """The pickle describes a numpy object that is not a plain numeric array."""


class PickledDtype:
    """Stand-in for ``numpy.dtype(spec, align, copy)`` followed by ``__setstate__``."""

    dtype: np.dtype | None = None  # the checked dtype, once known

    def __init__(self, spec: Any, align: Any = False, copy: Any = True):
        if not isinstance(spec, str) or spec not in SAFE_TYPE_CODES:
            raise UnsafeContent(
                f"numpy dtype {spec!r} is not a plain numeric or bool type "
                f"(allowed: {', '.join(sorted(SAFE_TYPE_CODES))})"
            )
        self.dtype = np.dtype(spec)

    def __setstate__(self, state: Any) -> None:
        """state: (3, byteorder, subarray, names, fields, elsize, alignment, flags[, metadata])."""
        base = self.dtype
        if base is None:
            raise UnsafeContent("a numpy dtype without a type code")
        if not isinstance(state, tuple) or len(state) not in (8, 9) or _int(state[0]) not in (3, 4):
            raise UnsafeContent(f"numpy dtype {base.str} with an unknown state layout")
        _version, order, subarray, names, fields, elsize, alignment, flags = state[:8]
        if any(v is not None for v in (subarray, names, fields, *state[8:])):
            raise UnsafeContent(f"numpy dtype {base.str} with fields, a sub-array or metadata")
        if _int(flags) != base.flags:
            raise UnsafeContent(f"numpy dtype {base.str} with altered flags {flags!r}")
        if _int(elsize) not in (-1, base.itemsize) or _int(alignment) not in (-1, base.alignment):
            raise UnsafeContent(f"numpy dtype {base.str} with item size {elsize!r}")
        if not isinstance(order, str) or order not in _BYTE_ORDERS:
            raise UnsafeContent(f"numpy dtype {base.str} with byte order {order!r}")
        self.dtype = base.newbyteorder(order) if order in "<>" else base.newbyteorder("=")


class PickledArray:
    """Stand-in for ``numpy.ndarray`` as ``_reconstruct`` makes it before ``__setstate__``."""

    array: np.ndarray | None = None

    def __setstate__(self, state: Any) -> None:
        """state: (1, shape, dtype, is_fortran, raw bytes)."""
        self.array = _build_array(state)


def _int(value: Any) -> int | None:
    """``value`` if it is a plain int, else None (never compares foreign objects)."""
    return value if type(value) is int else None


def _build_array(state: Any) -> np.ndarray:
    if not isinstance(state, tuple) or len(state) != 5 or _int(state[0]) != 1:
        raise UnsafeContent("a numpy array with an unknown state layout")
    _version, shape, dtype, fortran, raw = state
    if (
        not isinstance(shape, tuple)
        or len(shape) > MAX_NDIM
        or not all(type(n) is int and n >= 0 for n in shape)
    ):
        raise UnsafeContent(f"a numpy array with shape {shape!r}")
    if not isinstance(dtype, PickledDtype) or dtype.dtype is None:
        raise UnsafeContent(f"a numpy array of shape {shape} without a checked dtype")
    if type(fortran) is not bool or not isinstance(raw, (bytes, bytearray)):
        raise UnsafeContent(f"a numpy array of shape {shape} whose data is not raw bytes")
    expected = math.prod(shape) * dtype.dtype.itemsize
    if len(raw) != expected:
        raise UnsafeContent(
            f"a numpy array of shape {shape} {dtype.dtype.str} needs {expected} bytes "
            f"but holds {len(raw)}"
        )
    flat = np.frombuffer(bytes(raw), dtype=dtype.dtype)
    return flat.reshape(shape, order="F" if fortran else "C").copy()


def reconstruct(cls: Any, shape: Any = (0,), typecode: Any = b"b") -> PickledArray:
    """Stand-in for ``numpy.core.multiarray._reconstruct(ndarray, (0,), b'b')``."""
    if cls is not PickledArray:
        raise UnsafeContent(f"numpy _reconstruct of {cls!r}; only plain arrays are read")
    return PickledArray()


def scalar(dtype: Any, data: Any = None) -> np.generic:
    """Stand-in for ``numpy.core.multiarray.scalar(dtype, raw bytes)``."""
    if not isinstance(dtype, PickledDtype) or dtype.dtype is None:
        raise UnsafeContent("a numpy scalar without a checked dtype")
    if not isinstance(data, bytes) or len(data) != dtype.dtype.itemsize:
        raise UnsafeContent(f"a numpy {dtype.dtype.str} scalar whose data is not its raw bytes")
    return np.frombuffer(data, dtype=dtype.dtype)[0]


def empty_bytes(*args: Any) -> bytes:
    """Stand-in for ``bytes()``, how protocol 2 pickles an empty array's data (nothing else)."""
    if args:
        raise UnsafeContent(f"bytes{args!r:.40}; only bytes() of an empty array is read")
    return b""


def safe_globals() -> list[tuple[Any, str]]:
    """``torch.serialization.safe_globals`` entries: numpy's pickle names -> the stand-ins."""
    entries: list[tuple[Any, str]] = [
        (PickledArray, "numpy.ndarray"),
        (PickledDtype, "numpy.dtype"),
        (empty_bytes, "builtins.bytes"),
    ]
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        entries += [(reconstruct, f"{module}._reconstruct"), (scalar, f"{module}.scalar")]
    return entries


def materialize(obj: Any) -> Any:
    """Replace the stand-ins in a loaded object tree with numpy arrays and dtypes.

    Dicts and lists are updated in place (cycles are fine); tuples are rebuilt.
    Raises :class:`UnsafeContent` for an array whose data never arrived, or for a
    tree nested too deeply to walk.
    """
    try:
        return _materialize(obj, {})
    except RecursionError:
        raise UnsafeContent("containers nested too deeply") from None


def _materialize(obj: Any, seen: dict[int, Any]) -> Any:
    if isinstance(obj, PickledArray):
        if obj.array is None:
            raise UnsafeContent("a numpy array without data")
        return obj.array
    if isinstance(obj, PickledDtype):
        return obj.dtype
    if not isinstance(obj, (dict, list, tuple)):
        return obj
    if id(obj) in seen:
        return seen[id(obj)]
    seen[id(obj)] = obj
    if isinstance(obj, dict):
        for key, value in obj.items():
            obj[key] = _materialize(value, seen)
    elif isinstance(obj, list):
        obj[:] = [_materialize(value, seen) for value in obj]
    else:
        items = [_materialize(value, seen) for value in obj]
        if any(a is not b for a, b in zip(items, obj, strict=True)):
            seen[id(obj)] = tuple(items) if type(obj) is tuple else type(obj)(items)
    return seen[id(obj)]


NPY_HEADER_MAX_BYTES = 10_000  # numpy's own default limit on a .npy header


def read_npz(
    path: str | Path, fields: dict[str, tuple[tuple[int | None, ...], str]], max_bytes: int
) -> dict[str, np.ndarray]:
    """The arrays ``fields`` of the ``.npz`` file ``path``, checked before they are read.

    fields: name -> (shape, kinds): ``shape`` with ``None`` for any length, ``kinds`` the
    numpy kind letters allowed ("u", "i", "f", "b"). max_bytes: the most data one array
    may hold. Members not named are never read. Raises :class:`UnsafeContent` naming the
    field for a missing field, a dtype or shape other than expected, a size over
    ``max_bytes`` (whatever the zip or the header claims: nothing is allocated for it)
    or data shorter than declared; OSError if the file cannot be read.
    """
    try:
        archive = zipfile.ZipFile(path)
    except zipfile.BadZipFile as e:
        raise UnsafeContent(f"not an .npz file (a zip of .npy arrays): {e}") from None
    with archive:
        return {
            name: _read_member(archive, name, *want, max_bytes) for name, want in fields.items()
        }


def _read_member(
    archive: zipfile.ZipFile,
    name: str,
    shape: tuple[int | None, ...],
    kinds: str,
    max_bytes: int,
) -> np.ndarray:
    try:
        info = archive.getinfo(f"{name}.npy")
    except KeyError:
        raise UnsafeContent(f"field {name!r} is missing") from None
    limit = max_bytes + NPY_HEADER_MAX_BYTES + 128  # magic, header length, padding
    if info.file_size > limit:
        raise UnsafeContent(
            f"field {name!r} claims {info.file_size} bytes; at most {max_bytes} bytes of data "
            "are expected"
        )
    try:
        with archive.open(info) as f:
            version = np.lib.format.read_magic(f)
            read_header = {
                (1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0,
            }.get(version)
            if read_header is None:
                raise UnsafeContent(f"field {name!r}: .npy format version {version}")
            got, fortran, dtype = read_header(f, max_header_size=NPY_HEADER_MAX_BYTES)
            _check_member(name, got, dtype, shape, kinds, max_bytes)
            nbytes = math.prod(got) * dtype.itemsize
            data = f.read(nbytes)
    except (ValueError, zipfile.BadZipFile, EOFError, NotImplementedError) as e:
        raise UnsafeContent(f"field {name!r}: not a readable .npy array: {e}") from None
    if len(data) != nbytes:
        raise UnsafeContent(f"field {name!r}: {len(data)} bytes of data, {nbytes} declared")
    array = np.frombuffer(data, dtype=dtype).reshape(got, order="F" if fortran else "C")
    return array.copy()


def _check_member(
    name: str,
    got: Any,
    dtype: np.dtype,
    shape: tuple[int | None, ...],
    kinds: str,
    max_bytes: int,
) -> None:
    if dtype.str[1:] not in SAFE_TYPE_CODES or dtype.kind not in kinds:
        raise UnsafeContent(f"field {name!r} has dtype {dtype}; expected kind {kinds!r}")
    if not isinstance(got, tuple) or not all(type(n) is int and n >= 0 for n in got):
        raise UnsafeContent(f"field {name!r} has shape {got!r}")
    if len(got) != len(shape) or any(
        w is not None and n != w for n, w in zip(got, shape, strict=True)
    ):
        want = tuple("any" if w is None else w for w in shape)
        raise UnsafeContent(f"field {name!r} has shape {got}; expected {want}")
    nbytes = math.prod(got) * dtype.itemsize
    if nbytes > max_bytes:
        raise UnsafeContent(
            f"field {name!r} declares shape {got} {dtype} ({nbytes} bytes); at most "
            f"{max_bytes} bytes are expected"
        )
