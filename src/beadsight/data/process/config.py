"""How a raw recording becomes a dataset: :class:`ProcessConfig` and the choices it checks.

Its own module so that the stages of :mod:`beadsight.data.process.run` (labels, images, QA)
can take it without importing the module that runs them.
"""

from __future__ import annotations

from dataclasses import dataclass

from beadsight.config import ConfigError, _Serializable
from beadsight.data.recording.counter import FORCE_COUNTER_MODES

FORCE_INTERPOLATIONS = ("pchip", "cubic", "linear")
DECODE_SCALES = (1, 2, 4, 8)  # JPEG decode reductions OpenCV offers (IMREAD_REDUCED_*)


@dataclass(frozen=True)
class ProcessConfig(_Serializable):
    """How a raw recording becomes a dataset."""

    image_size: int = 256  # side of the dataset's square images, px
    preprocess: str = "reference"  # "reference", "none", or a fisheye lens .json path
    interpolation: str = "linear"  # reference unwarp sampling: "linear" or "reference" (bit-exact)
    resize: str = "supersample"  # "supersample" (fast, antialiased), "area", "linear"
    force_interpolation: str = "pchip"  # "pchip", "cubic" (reference) or "linear"
    max_force_gap_s: float = 0.5  # frames inside a longer gap between scale readings are invalid
    camera_delay_s: float = 0.0  # capture-to-timestamp latency subtracted from frame times
    decode_scale: int = 0  # JPEG decode reduction 1, 2, 4, 8; 0 = largest that keeps detail
    workers: int = 0  # preprocessing threads; 0 = one per CPU core
    batch_frames: int = 64  # frames per dataset append
    compression: str | None = None  # HDF5 compression of frames ("gzip", "lzf", None)
    force_counter: str = "auto"  # the reference scale sketch's +10000*i counter: auto, on, off
    scale_capacity_n: float = 50.0  # readings beyond this are implausible: warned, frames invalid

    def __post_init__(self) -> None:
        if int(self.image_size) != self.image_size or self.image_size < 8:
            raise ConfigError(f"image_size must be an integer >= 8, got {self.image_size}")
        if self.force_interpolation not in FORCE_INTERPOLATIONS:
            raise ConfigError(
                f"force_interpolation must be one of {FORCE_INTERPOLATIONS}, got "
                f"{self.force_interpolation!r}"
            )
        if not self.max_force_gap_s > 0:
            raise ConfigError(f"max_force_gap_s must be > 0, got {self.max_force_gap_s}")
        if self.decode_scale not in (0, *DECODE_SCALES):
            raise ConfigError(
                f"decode_scale must be 0 (auto), 1, 2, 4 or 8, got {self.decode_scale}"
            )
        if self.workers < 0 or self.batch_frames < 1:
            raise ConfigError("workers must be >= 0 and batch_frames >= 1")
        if self.compression not in (None, "gzip", "lzf"):
            raise ConfigError(f"compression must be gzip, lzf or None, got {self.compression!r}")
        if self.force_counter not in FORCE_COUNTER_MODES:
            raise ConfigError(
                f"force_counter must be one of {FORCE_COUNTER_MODES}, got {self.force_counter!r}"
            )
        if not self.scale_capacity_n > 0:
            raise ConfigError(f"scale_capacity_n must be > 0 N, got {self.scale_capacity_n}")
