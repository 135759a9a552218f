"""How a :class:`~beadsight.live.sensor.LiveSensor` runs: :class:`LiveSettings`.

One frozen dataclass, validated when made, for everything but the checkpoint and the
source: how the predictor's runtime is chosen (passed to
:meth:`~beadsight.inference.predictor.PressurePredictor.from_checkpoint`), how frames
become model input (:mod:`beadsight.inference.frames`), the source's options, and the
fault timing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from beadsight.config import ConfigError
from beadsight.inference.backend import BACKENDS, PRECISIONS
from beadsight.inference.frames import check_preprocess
from beadsight.inference.predictor import PredictorSettings

FIRST_FRAME_TIMEOUT_S = 15.0  # a source that gives no frame this long after opening fails
NO_SIGNAL_AFTER_S = 1.0  # no new frame for this long -> state "no_signal"
RECONNECT_INITIAL_S = 0.5  # first wait before reopening a lost camera; doubles per try
RECONNECT_MAX_S = 8.0  # longest wait between reopening attempts
# a rest-referenced model reads nothing until the rest is taken from still frames (or a file)
LIVE_PREDICTOR = PredictorSettings(initial_rest="wait")


@dataclass(frozen=True)
class LiveSettings:
    """Settings of live sensing (everything but the checkpoint and the source)."""

    backend: str = "auto"  # auto | torch | onnx | openvino | cuda
    precision: str = "auto"  # auto | fp32 | bf16
    device: str | None = None  # torch device of the torch/cuda backends
    exported_model: str | None = None  # an exported .onnx / OpenVINO .xml of the checkpoint
    threads: int | None = None  # backend CPU threads (None: $OMP_NUM_THREADS, else all cores)
    preprocess: str = "auto"  # auto | none | reference | reference-linear | lens .json
    source_fps: float | None = None  # simulator rate (None: 30) / rate asked of a camera
    loop: bool = False  # restart a video file at its end
    seed: int = 0  # the simulator's seed
    predictor: PredictorSettings = field(default_factory=lambda: LIVE_PREDICTOR)  # gaps, contact
    first_frame_timeout_s: float = FIRST_FRAME_TIMEOUT_S  # no first frame this long: error
    no_signal_after_s: float = NO_SIGNAL_AFTER_S  # no new frame this long: state no_signal
    reconnect_initial_s: float = RECONNECT_INITIAL_S  # first wait before reopening a camera
    reconnect_max_s: float = RECONNECT_MAX_S  # longest wait; the wait doubles per attempt
    max_readings: int | None = None  # end sensing (state "ended") after this many readings
    health: bool = True  # track drift health between rest states (beadsight.health)
    rest_file: str | None = None  # a stored rest reference .npz (None: taken at start-up)
    sim_drift: str | None = None  # the simulator's drift (sim/drift.py), e.g. "settle,bump"

    def __post_init__(self) -> None:
        if self.backend not in ("auto", *BACKENDS):
            raise ConfigError(f"backend must be 'auto' or one of {BACKENDS}, got {self.backend!r}")
        if self.precision not in ("auto", *PRECISIONS):
            raise ConfigError(
                f"precision must be 'auto' or one of {PRECISIONS}, got {self.precision!r}"
            )
        object.__setattr__(self, "preprocess", _checked(check_preprocess, self.preprocess))
        if self.exported_model is not None:
            object.__setattr__(self, "exported_model", str(self.exported_model))
        if not isinstance(self.predictor, PredictorSettings):
            raise ConfigError(f"predictor must be PredictorSettings, got {self.predictor!r}")
        for name in ("first_frame_timeout_s", "no_signal_after_s", "reconnect_initial_s"):
            _positive(name, getattr(self, name))
        _positive("reconnect_max_s", self.reconnect_max_s)
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ConfigError(
                f"reconnect_max_s ({self.reconnect_max_s}) must not be below "
                f"reconnect_initial_s ({self.reconnect_initial_s})"
            )
        if self.source_fps is not None:
            _positive("source_fps", self.source_fps)
        if self.sim_drift is not None:
            from beadsight.sim.drift import parse_drift

            object.__setattr__(self, "sim_drift", parse_drift(self.sim_drift).describe())
        if self.rest_file is not None:
            object.__setattr__(self, "rest_file", str(self.rest_file))
        for name in ("max_readings", "threads"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
                raise ConfigError(f"{name} must be an integer >= 1 or None, got {value!r}")

    def predictor_arguments(self) -> dict[str, Any]:
        """Keyword arguments of ``PressurePredictor.from_checkpoint`` (after the checkpoint)."""
        return {
            "backend": self.backend,
            "precision": self.precision,
            "device": self.device,
            "exported_model": self.exported_model,
            "threads": self.threads,
            "settings": self.predictor,
        }


def _checked(check, value):
    try:
        return check(value)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise ConfigError(f"{name} must be a number > 0, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be finite, got {value!r}")
