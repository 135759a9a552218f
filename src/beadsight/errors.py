"""Error types shown to users as one clear line (the CLI prints them without a traceback).

Kept free of heavy imports (no torch) so device tools start quickly.
"""

from __future__ import annotations

from beadsight.config import ConfigError


class BeadSightError(Exception):
    """Base for errors whose message names the file, device or field and what was expected."""


# CheckpointError and DatasetError are ValueErrors, so ValueError covers them.
USER_ERRORS: tuple[type[BaseException], ...] = (
    BeadSightError,
    ConfigError,
    FileNotFoundError,
    ValueError,
)
