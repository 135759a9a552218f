"""The runtime interface: what every backend of :mod:`beadsight.inference.runtimes` offers.

A backend runs one checkpoint's :class:`~beadsight.model.FramesToPressure` on numpy
windows, statelessly (:meth:`Backend.run`) or streaming (:meth:`Backend.run_incremental`).
A rest-referenced model's input starts with the rest image; streaming takes the rest
image apart from the window, so runtimes that keep state prepare it once per change.
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
    ``span``: frames per window; ``frames``: how many of them the network sees;
    ``rest``: 1 if the input starts with a rest image; ``inputs``: rest + span.
    """

    name = "base"
    precisions: tuple[str, ...] = PRECISIONS  # the precisions this runtime can run
    batched = False  # True: _run accepts (B, inputs, S, S, 3) for any B

    def __init__(self, model: PressureModel, precision: str = "fp32"):
        if precision not in self.precisions:
            raise ConfigError(
                f"{self.name}: precision must be one of {self.precisions}, got {precision!r}"
            )
        self.model = model
        self.precision = precision
        self.span = model.span
        self.frames = model.frames
        self.rest = model.rest
        self.inputs = model.inputs
        self.image_size = model.image_size
        self._shape = (1, self.inputs, self.image_size, self.image_size, 3)

    def describe(self) -> str:
        return f"{self.name}/{self.precision}"

    def _check(self, images: np.ndarray, shape: tuple[int, ...] | None = None) -> None:
        shape = shape or self._shape
        if getattr(images, "shape", None) != shape or images.dtype != np.uint8:
            what = (
                "images (rest image + window)" if self.rest and shape == self._shape else "window"
            )
            raise ValueError(
                f"{what}: expected {shape} uint8 RGB, got "
                f"{getattr(images, 'shape', None)} {getattr(images, 'dtype', type(images))}"
            )

    def _check_rest(self, rest: np.ndarray | None) -> None:
        if not self.rest:
            if rest is not None:
                raise ValueError("rest: this model is not rest-referenced; pass no rest image")
            return
        s = self.image_size
        if rest is None:
            raise ValueError(
                "rest: this model is rest-referenced and needs a rest image of the unloaded "
                f"pouch, ({s}, {s}, 3) uint8 RGB"
            )
        if getattr(rest, "shape", None) != (s, s, 3) or rest.dtype != np.uint8:
            raise ValueError(
                f"rest: expected ({s}, {s}, 3) uint8 RGB, got {getattr(rest, 'shape', None)} "
                f"{getattr(rest, 'dtype', type(rest))}"
            )

    def run(self, images: np.ndarray) -> np.ndarray:
        """images: (1, inputs, S, S, 3) uint8 RGB (a rest-referenced model's rest image
        first, then the window oldest first) -> (1, S, S) float32 kPa."""
        self._check(images)
        return self._run(np.ascontiguousarray(images))

    def run_batch(self, images: np.ndarray, batch_size: int = 16) -> np.ndarray:
        """images: (B, inputs, S, S, 3) uint8 RGB (each as :meth:`run` takes it) ->
        (B, S, S) float32 kPa. Runtimes with a batch axis run ``batch_size`` inputs per
        call; the others run them one by one. The offline path (evaluate, predict)."""
        shape = getattr(images, "shape", None)
        if shape is None or tuple(shape[1:]) != self._shape[1:] or images.dtype != np.uint8:
            raise ValueError(
                f"images: expected (B, {', '.join(map(str, self._shape[1:]))}) uint8 RGB, "
                f"got {shape} {getattr(images, 'dtype', type(images))}"
            )
        out = np.empty((len(images), self.image_size, self.image_size), dtype=np.float32)
        step = max(int(batch_size), 1) if self.batched else 1
        for i in range(0, len(images), step):
            chunk = np.ascontiguousarray(images[i : i + step])
            out[i : i + step] = self._run(chunk) if step > 1 else self.run(chunk)
        return out

    def run_incremental(
        self, window: np.ndarray, new_frames: int, rest: np.ndarray | None = None
    ) -> np.ndarray:
        """window: (1, span, S, S, 3) uint8 RGB, oldest first, where only the last
        ``new_frames`` frames differ from the previous call's window shifted by
        ``new_frames`` (``>= span``: all new); rest: the (S, S, 3) uint8 RGB rest image
        (rest-referenced models only). Stateless backends just call :meth:`run`."""
        self._check(window, (1, self.span, *self._shape[2:]))
        self._check_rest(rest)
        if rest is None:
            return self.run(window)
        return self.run(np.concatenate([rest[None, None], window], axis=1))

    def _run(self, window: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def close(self) -> None:
        """Release the backend's resources (sessions, GPU memory)."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}>"
