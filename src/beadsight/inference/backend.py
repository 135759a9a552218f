"""The runtime interface: what every backend of :mod:`beadsight.inference.runtimes` offers.

A backend runs one checkpoint's :class:`~beadsight.model.FramesToPressure` on numpy
windows, statelessly (:meth:`Backend.run`) or streaming (:meth:`Backend.run_incremental`).
"""

from __future__ import annotations

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.errors import BeadSightError, ConfigError
from beadsight.inference.config import BACKENDS, PRECISIONS

__all__ = ["BACKENDS", "PRECISIONS", "Backend", "BackendError", "BackendUnavailableError"]


class BackendError(BeadSightError):
    """A backend cannot be used for this checkpoint (unavailable, or it disagrees)."""


class BackendUnavailableError(BackendError):
    """The backend or precision is not installed or not supported by this hardware."""


class Backend:
    """Runs one checkpoint's FramesToPressure on numpy windows.

    Subclasses implement :meth:`_run`; ``name`` and ``precision`` describe them.
    ``span``: frames per window; ``frames``: how many of them the network sees.
    """

    name = "base"

    def __init__(self, model: PressureModel, precision: str = "fp32"):
        if precision not in PRECISIONS:
            raise ConfigError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self.model = model
        self.precision = precision
        self.span = model.span
        self.frames = model.frames
        self.image_size = model.image_size
        self._shape = (1, self.span, self.image_size, self.image_size, 3)

    def describe(self) -> str:
        return f"{self.name}/{self.precision}"

    def _check(self, window: np.ndarray) -> None:
        if getattr(window, "shape", None) != self._shape or window.dtype != np.uint8:
            raise ValueError(
                f"window: expected {self._shape} uint8 RGB, got "
                f"{getattr(window, 'shape', None)} {getattr(window, 'dtype', type(window))}"
            )

    def run(self, window: np.ndarray) -> np.ndarray:
        """window: (1, span, S, S, 3) uint8 RGB, oldest first -> (1, S, S) float32 kPa."""
        self._check(window)
        return self._run(np.ascontiguousarray(window))

    def run_incremental(self, window: np.ndarray, new_frames: int) -> np.ndarray:
        """Like :meth:`run`, where only the last ``new_frames`` frames of ``window``
        differ from the previous call's window shifted by ``new_frames`` (``>= span``:
        all new). Stateless backends just call :meth:`run`."""
        return self.run(window)

    def _run(self, window: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def close(self) -> None:
        """Release the backend's resources (sessions, GPU memory)."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}>"
