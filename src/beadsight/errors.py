"""The error family shown to users, and how the command line tells them from bugs.

Every error a user can cause (a bad setting, file or device) derives from
:class:`BeadSightError` and names the file, device or field and what was expected; the
CLI prints it as one line. Any other exception is a bug in beadsight: the CLI prints
"internal error" and, under ``-v``, the traceback.

Errors about a bad value (:class:`ConfigError`, ``CheckpointError``, ``DatasetError``, ...)
also derive from ``ValueError``.

Kept free of imports (no torch, no numpy) so every module and the CLI's help can use it.
"""

from __future__ import annotations


class BeadSightError(Exception):
    """Base for errors whose message names the file, device or field and what was expected."""


class ConfigError(BeadSightError, ValueError):
    """A setting is out of range or of the wrong type (names the field and what it takes)."""


# What the CLI prints as one line without a traceback: errors of the user's making. A
# missing input file is one even when a library (h5py, OpenCV) raises it.
USER_ERRORS: tuple[type[BaseException], ...] = (BeadSightError, FileNotFoundError)
