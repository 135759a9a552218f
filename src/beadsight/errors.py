"""Error types shown to users as one clear line (the CLI prints them without a traceback)."""

from __future__ import annotations

from beadsight.checkpoint import CheckpointError
from beadsight.config import ConfigError
from beadsight.data.dataset import DatasetError


class BeadSightError(Exception):
    """Base for errors whose message names the file, device or field and what was expected."""


USER_ERRORS: tuple[type[BaseException], ...] = (
    BeadSightError,
    CheckpointError,
    ConfigError,
    DatasetError,
    FileNotFoundError,
    ValueError,
)
