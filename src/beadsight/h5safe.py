"""Reading HDF5 files this project did not write, without trusting what they claim.

An HDF5 header can claim any shape: a 7 MB file can say a dataset holds 10^9 rows,
and ``ds[()]`` then allocates tens of GB before HDF5 notices the data is not there.
Links can loop or lead into other files, and a dataset's raw data can live in an
external file. The readers (datasets, reference files, live readings) therefore
open files and look datasets up through these functions, which check every claim
against the file before a byte is read, and raise the caller's error class with a
message naming the file and the field.
"""

from __future__ import annotations

import math
import os
import stat
from pathlib import Path

import h5py

# A filter pipeline expands stored bytes by at most this much: deflate cannot exceed
# ~1032:1, and the other filters are held to the same bound.
MAX_FILTER_RATIO = 1100
# Claims up to this size are not checked against storage (small unwritten datasets read
# as their fill value, which is harmless).
UNCHECKED_CLAIM_BYTES = 1 << 20
MAX_ATTRIBUTE_BYTES = 1 << 20  # an attribute holds metadata: anything larger is refused


def open_h5(
    path: Path,
    kind: str,
    error: type[Exception],
    missing: type[Exception] | None = None,
) -> h5py.File:
    """Open ``path`` read-only; ``kind`` names it in errors ("dataset file").

    Raises ``missing`` (default ``error``) if there is nothing at ``path``, and
    ``error`` for a directory, a device or FIFO, or a file HDF5 cannot open.
    """
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise (missing or error)(f"{path}: {kind} not found") from None
    except OSError as e:
        raise error(f"{path}: cannot read {kind} ({os.strerror(e.errno or 0)})") from None
    if stat.S_ISDIR(mode):
        raise error(f"{path}: is a directory; expected a {kind} (an HDF5 file)")
    if not stat.S_ISREG(mode):
        raise error(f"{path}: not a regular file; expected a {kind} (an HDF5 file)")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise error(
            f"{path}: not a readable HDF5 file ({e}); the file may be truncated or corrupt"
        ) from None
    try:
        check_attributes(f, path, error)
    except BaseException:
        f.close()
        raise
    return f


def find_dataset(
    f: h5py.File,
    names: tuple[str, ...],
    path: Path,
    error: type[Exception],
    expected: str = "numbers",
) -> h5py.Dataset | None:
    """The first of ``names`` present in ``f`` as a checked dataset, or None.

    ``expected`` describes the content for errors ("(N,) float64 force").
    A name that is a group, a link leading out of the file or into a loop, or a
    dataset whose claimed size the file cannot hold raises ``error``.
    """
    for name in names:
        try:
            link = f.get(name, getlink=True)
        except (KeyError, RuntimeError, OSError, ValueError) as e:
            raise error(f"{path}: cannot look up '{name}' ({e})") from None
        if link is None:
            continue
        if isinstance(link, h5py.ExternalLink):
            raise error(
                f"{path}: '{name}' is an external link to {link.filename}:{link.path}; "
                f"expected a dataset of {expected} stored in this file"
            )
        try:
            obj = f[name]
        except (KeyError, RuntimeError, OSError, ValueError) as e:
            raise error(
                f"{path}: '{name}' is a link that cannot be followed ({e}); "
                f"expected a dataset of {expected}"
            ) from None
        if not isinstance(obj, h5py.Dataset):
            raise error(f"{path}: '{name}' is a group; expected a dataset of {expected}")
        check_dataset(obj, name, path, error)
        return obj
    return None


def check_dataset(ds: h5py.Dataset, name: str, path: Path, error: type[Exception]) -> None:
    """Raise ``error`` unless the file really holds the bytes ``ds`` claims."""
    if ds.dtype.hasobject or ds.dtype.itemsize == 0:
        raise error(f"{path}: '{name}' has dtype {ds.dtype}; expected fixed-size numbers")
    plist = ds.id.get_create_plist()
    layout = plist.get_layout()
    if layout == h5py.h5d.VIRTUAL:
        raise error(f"{path}: '{name}' is a virtual dataset; expected data stored in this file")
    if plist.get_external_count():
        raise error(
            f"{path}: '{name}' keeps its data in an external file; expected data in this file"
        )
    claimed = math.prod(ds.shape or ()) * ds.dtype.itemsize  # shape None: an empty dataspace
    stored = ds.id.get_storage_size()
    file_size = path.stat().st_size
    offset = ds.id.get_offset() if layout == h5py.h5d.CONTIGUOUS else None
    if stored > file_size or (offset is not None and offset + stored > file_size):
        raise error(
            f"{path}: '{name}' claims {_size(stored)} of storage in a {_size(file_size)} file; "
            "the file is truncated or forged"
        )
    ratio = MAX_FILTER_RATIO if plist.get_nfilters() else 1
    if claimed > UNCHECKED_CLAIM_BYTES and claimed > stored * ratio:
        raise error(
            f"{path}: '{name}' claims shape {ds.shape} ({_size(claimed)}) but the file stores "
            f"only {_size(stored)} of it; the file is truncated or forged"
        )
    check_attributes(ds, path, error)


def check_attributes(obj: h5py.HLObject, path: Path, error: type[Exception]) -> None:
    """Raise ``error`` if an attribute of ``obj`` claims more than MAX_ATTRIBUTE_BYTES."""
    try:
        for key in obj.attrs:
            attr = obj.attrs.get_id(key)
            size = math.prod(attr.shape or ()) * attr.dtype.itemsize
            if size > MAX_ATTRIBUTE_BYTES:
                raise error(
                    f"{path}: attribute '{key}' of '{obj.name}' claims {_size(size)}; "
                    f"expected at most {_size(MAX_ATTRIBUTE_BYTES)} of metadata"
                )
    except (KeyError, RuntimeError, OSError) as e:
        raise error(f"{path}: unreadable attributes on '{obj.name}' ({e})") from None


def _size(n: int) -> str:
    """A byte count for people: "512 bytes", "6.6 MiB", "7.3 GiB"."""
    if n < 1024:
        return f"{n} bytes"
    exponent = min(int(math.log(n, 1024)), 4)
    return f"{n / 1024**exponent:.1f} {('KiB', 'MiB', 'GiB', 'TiB')[exponent - 1]}"
