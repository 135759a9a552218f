"""Writing files so that a crash, Ctrl-C or a full disk never leaves a damaged file
under its final name. The only place in beadsight that renames a file into place.

Two patterns:

* **Atomic replace** (small files: JSON, checkpoints, exported models): write a hidden
  temporary file in the same folder, fsync it, rename it over the target, fsync the
  folder. :func:`atomic_write` and its ``_bytes`` / ``_text`` / ``_json`` forms.
* **Partial file** (long recordings written as data arrives): write ``NAME.partial``,
  and rename it to ``NAME`` with :func:`finish_partial` only after the last write
  succeeded. Whatever was recorded before a crash stays readable in ``NAME.partial``.

Reading untrusted files: :func:`require_regular_file` refuses FIFOs and devices before
they are opened, :func:`read_bounded` also files over a size limit.

A write that fails (disk full, quota, file size limit) raises :class:`WriteError`
naming the file and the cause; the temporary file is removed and the target is
left as it was.
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from beadsight.errors import BeadSightError

PARTIAL_SUFFIX = ".partial"
TEMP_SUFFIX = ".tmp"  # hidden ".NAME.<random>.tmp" files of atomic writes
MAX_JSON_BYTES = 64 * 1024 * 1024  # a settings/metadata JSON file larger than this is refused


class WriteError(BeadSightError):
    """A file could not be written (disk full, no permission, ...); names the file."""


class OutputExistsError(BeadSightError):
    """An output would replace an existing file (or is a folder); names it and the fix."""


class Closes:
    """Used as a context manager, the object is ``close()``d when the block ends, however
    it ends (a file opened for reading, a server, a predictor's runtime)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ClosesOrAborts:
    """A writer used as a context manager: ``close()`` when the block succeeds (the file
    gets its final name), ``abort()`` when it raises (nothing half-written is kept under
    the final name)."""

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def require_regular_file(
    path: str | Path, error: type[BeadSightError] = BeadSightError, what: str = "a file"
) -> os.stat_result:
    """``path``'s stat if it is a regular file; ``error`` naming it otherwise. A FIFO, a
    device (``/dev/zero``) or a socket would block a reader or never end; checked before
    anything opens it (opening a FIFO blocks)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: file not found (expected {what})") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({describe_os_error(e)})") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO or device)"
        raise error(f"{path}: is {kind}; expected {what}")
    return st


def read_bounded(
    path: str | Path,
    max_bytes: int,
    error: type[BeadSightError] = BeadSightError,
    what: str = "a file",
) -> bytes:
    """The bytes of regular file ``path`` (:func:`require_regular_file`), at most
    ``max_bytes``; a larger file (or one that grows past it while read) is ``error``."""
    size = require_regular_file(path, error, what).st_size
    data = b""
    if size <= max_bytes:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    if size > max_bytes or len(data) > max_bytes:
        raise error(
            f"{path}: {max(size, len(data))} bytes, more than {max_bytes} for {what}; "
            "not read (a corrupt or forged file?)"
        )
    return data


def read_json_object(
    path: str | Path, error: type[BeadSightError] = BeadSightError, what: str = "a JSON object"
) -> dict[str, Any]:
    """The JSON object in ``path``; ``error`` naming the file if it is missing, not a
    regular file, over :data:`MAX_JSON_BYTES`, not JSON, or not an object (``what`` says
    what was expected)."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        raise error(f"{path}: file not found")
    try:
        data = json.loads(read_bounded(path, MAX_JSON_BYTES, error, what).decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise error(f"{path}: expected {what}")
    return data


def refuse_existing(path: str | Path, overwrite: bool = False, flag: str = "--overwrite") -> Path:
    """Refuse to write ``path`` over anything that exists unless ``overwrite`` (never a folder)."""
    path = Path(path)
    if path.is_dir():
        raise OutputExistsError(f"{path}: is a folder; expected the name of a file to write")
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise OutputExistsError(
            f"{path}: already exists; choose another output name, or pass {flag} to replace it"
        )
    return path


def prepare_output_folder(
    path: str | Path, overwrite: bool = False, flag: str = "--overwrite"
) -> Path:
    """Create output folder ``path``; the one rule for commands that write a folder.

    A file of that name is refused (it is not a folder), and so is a folder that already
    holds anything unless ``overwrite``: the command would replace files it did not write.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: is a file; expected a folder to write into")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{path}: folder exists and is not empty; choose another output folder, or pass "
            f"{flag} to replace its files"
        )
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise write_error(path, e) from e
    return path


def describe_os_error(e: OSError) -> str:
    """A short cause for a failed write: 'disk full', 'file size limit reached', ..."""
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        return "disk full"
    if e.errno == errno.EFBIG:
        return "file size limit reached"
    return e.strerror or str(e)


def describe_write_failure(e: BaseException) -> str:
    """The cause of a failed write from any library's error: ``describe_os_error`` of its
    errno, also when the errno is only in the text (h5py: ``... errno = 28, ...``)."""
    number = getattr(e, "errno", None)
    if not number:
        match = re.search(r"errno = (\d+)", str(e))
        number = int(match.group(1)) if match else None
    if number:
        return describe_os_error(OSError(number, os.strerror(number)))
    text = str(e)
    return text.splitlines()[0] if text else type(e).__name__


def write_error(path: str | Path, e: OSError) -> WriteError:
    """The :class:`WriteError` for ``e`` raised while writing ``path``."""
    return WriteError(f"could not write {path}: {describe_os_error(e)}")


def default_file_mode() -> int:
    """The mode a plain ``open(path, "w")`` would give (0666 less the umask)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def fsync_dir(path: str | Path) -> None:
    """fsync a folder so that a rename in it survives a power cut (no-op where unsupported)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def atomic_write(
    path: str | Path, write: Callable[[IO[bytes]], Any], mode: int | None = None
) -> Path:
    """Call ``write(f)`` on a temporary binary file beside ``path``, then rename it into place.

    ``mode``: the file's permission bits (default: as ``open`` would make them).
    A failure of any kind removes the temporary file and leaves ``path`` untouched;
    an ``OSError`` becomes :class:`WriteError`.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMP_SUFFIX, dir=path.parent)
    except OSError as e:
        raise write_error(path, e) from e
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, default_file_mode() if mode is None else mode)
        os.replace(tmp, path)
    except BaseException as e:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise write_error(path, e) from e
        raise
    fsync_dir(path.parent)
    return path


def atomic_write_bytes(path: str | Path, data: bytes, mode: int | None = None) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda f: f.write(data), mode)


def atomic_write_text(path: str | Path, text: str, mode: int | None = None) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"), mode)


def atomic_write_json(
    path: str | Path, obj: Any, *, strict: bool = False, mode: int | None = None
) -> Path:
    """Write ``obj`` as indented JSON, atomically.

    ``strict``: refuse NaN/inf (``ValueError``) instead of writing non-standard JSON, and
    refuse values JSON cannot hold; otherwise they are written with ``str()``.
    """
    if strict:
        text = json.dumps(obj, indent=2, allow_nan=False)
    else:
        text = json.dumps(obj, indent=2, default=str)
    return atomic_write_text(path, text + "\n", mode)


def partial_path(path: str | Path) -> Path:
    """Where a file being recorded lives until it is finished: ``NAME.partial``."""
    path = Path(path)
    return path.with_name(path.name + PARTIAL_SUFFIX)


def finish_partial(partial: str | Path, path: str | Path) -> Path:
    """Rename a finished ``partial`` file to its final name ``path`` (and fsync the folder)."""
    path = Path(path)
    try:
        with open(partial, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(partial, path)
    except OSError as e:
        raise write_error(path, e) from e
    fsync_dir(path.parent)
    return path


@contextmanager
def os_errors_as_write_errors(path: str | Path) -> Iterator[None]:
    """Turn an ``OSError`` raised inside the block into a :class:`WriteError` naming ``path``."""
    try:
        yield
    except OSError as e:
        raise write_error(path, e) from e


def remove_stale_temps(folder: str | Path, name: str) -> list[Path]:
    """Remove temporary files an interrupted :func:`atomic_write` of ``folder/name`` left."""
    removed = []
    for tmp in Path(folder).glob(f".{name}.*{TEMP_SUFFIX}"):
        try:
            tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass
    return removed


def free_bytes(folder: str | Path) -> int:
    """Bytes an unprivileged writer may still write in ``folder``'s file system.

    For writers that stop cleanly before a disk fills (HDF5 cannot recover from a write
    that fails half-way); where the file system cannot tell, a very large number.
    """
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return sys.maxsize
