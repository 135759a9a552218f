"""What ``beadsight demo`` runs (:class:`DemoConfig`), its error, and the names and
sizes of its report. Imports nothing heavy, so the command line reads its defaults here."""

from __future__ import annotations

from dataclasses import dataclass

from beadsight.config import _Serializable
from beadsight.errors import BeadSightError

DEMO_SEED = 90_210  # held-out presses; training sets must use other seeds
TRAIN_DEMO_SEED = 31_337  # the training set of ``demo --train``
DEFAULT_OUT = "beadsight-demo"
MARKER = "demo.json"  # a folder holding this file is a demo report and may be overwritten
HELDOUT_FILE = "heldout.h5"
ANIMATION_FILE = "animation.gif"
ANIMATION_MAX_FRAMES = 72  # at most this many (consecutive) animated frames in the report
INDEX_FILE = "index.html"
# The reference training recipe (reference-facts section 7), for the time estimate.
REFERENCE_PRESSES = 500
REFERENCE_EPOCHS = 100
REFERENCE_BATCH = 64
REFERENCE_IMAGE_SIZE = 256
REFERENCE_WIDTH = 16
TIMING_BATCH = 2  # samples per timed step of the reference-size network
TRAIN_DEMO_VAL_STRIDE = 4  # demo --train validates on every 4th window (time)
DEFAULT_TRAIN_FRACTION = 0.7


class DemoError(BeadSightError):
    """The demo cannot run as asked (missing model, bad folder, bad sizes); says why."""


@dataclass(frozen=True)
class DemoConfig(_Serializable):
    """What ``beadsight demo`` runs. Defaults fit in ~3 minutes on a 2-core CPU."""

    out: str = DEFAULT_OUT  # report folder
    checkpoint: str | None = None  # None: the shipped model
    presses: int = 10  # held-out presses to simulate
    pouches: int = 3  # ... on this many fresh pouches (never seen in training)
    seed: int = DEMO_SEED  # of the held-out presses
    beads: int | None = None  # None: the model's training pouch, else the 100-bead preset
    max_frames: int | None = 800  # frames evaluated, spread evenly over the presses
    batch_size: int = 16
    device: str = "auto"
    # keep the simulated datasets in the report folder: the log, metrics.json and the page
    # name heldout.h5, and `beadsight evaluate --data heldout.h5` reproduces the figures
    keep_data: bool = True
    animation_frames: int = ANIMATION_MAX_FRAMES  # consecutive frames in animation.gif
    progress: bool = True
    # --- demo --train ---
    train: bool = False
    train_presses: int = 16  # simulated training presses
    train_pouches: int = 4  # ... spread over this many pouches
    train_steps: int = 40  # optimizer steps
    train_batch_size: int = 8
    train_width: int = 8
    train_image_size: int = 64

    def __post_init__(self) -> None:
        for name, low in (
            ("presses", 1),
            ("pouches", 1),
            ("train_pouches", 1),
            ("batch_size", 1),
            ("train_presses", 3),
            ("animation_frames", 1),
            ("train_steps", 1),
            ("train_batch_size", 1),
            ("train_width", 1),
            ("train_image_size", 8),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < low:
                raise DemoError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise DemoError(f"max_frames must be >= 1 or None, got {self.max_frames!r}")
