"""Settings of :func:`~beadsight.evaluation.evaluate.evaluate` (:class:`EvaluateConfig`)
and the defaults of :func:`~beadsight.evaluation.predict.predict_recording`, in one light
module (no torch) that both functions and the command line read."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from beadsight.errors import BeadSightError
from beadsight.inference.config import BACKENDS, INT8, PRECISIONS

SPLIT_CHOICES = ("test", "val", "all")  # presses evaluate scores
DEFAULT_SPLIT = "test"
DEFAULT_DEVICE = "auto"  # auto | cpu | cuda | cuda:N | mps
DEFAULT_BACKEND = "torch"  # the runtime offline scoring uses (live's names; "auto" too)
BACKEND_CHOICES = ("auto", *BACKENDS)
PRECISION_CHOICES = ("auto", *PRECISIONS, INT8)
EVALUATE_BATCH_SIZE = 16  # windows per forward pass
PREDICT_BATCH_SIZE = 8
PREDICT_PREPROCESS = "auto"  # auto | none | reference | reference-linear | lens .json


class EvaluationError(BeadSightError):
    """The checkpoint and the dataset cannot be evaluated together; the message says why."""


def check_runtime(backend: str, precision: str) -> None:
    """Raise EvaluationError naming ``--backend`` / ``--precision`` for unknown names."""
    if backend not in BACKEND_CHOICES:
        raise EvaluationError(
            f"--backend must be one of {', '.join(BACKEND_CHOICES)}, got {backend!r}"
        )
    if precision not in PRECISION_CHOICES:
        raise EvaluationError(
            f"--precision must be one of {', '.join(PRECISION_CHOICES)}, got {precision!r}"
        )


@dataclass(frozen=True)
class EvaluateConfig:
    """How :func:`~beadsight.evaluation.evaluate.evaluate` scores a checkpoint.

    The resolved config is written into ``metrics.json`` (``config``).
    """

    split: str = DEFAULT_SPLIT  # presses scored: test/val (the training run's split), all
    backend: str = DEFAULT_BACKEND  # runtime the model runs on (as `live --backend`)
    precision: str = "auto"  # fp32, bf16, int8 or auto (the backend's default)
    device: str = DEFAULT_DEVICE  # torch device of the torch/cuda runtimes
    batch_size: int = EVALUATE_BATCH_SIZE  # windows per call where the runtime batches
    max_frames: int | None = None  # score that many frames spread evenly over the split
    baselines: bool = False  # also score an all-zero map and the mean training label
    plots: bool = True  # write the PNG plots (with an output folder)
    resize: bool = False  # resize frames to the checkpoint's image size if they differ
    progress: bool = True  # progress bar
    report: bool = True  # write index.html (with an output folder)

    def __post_init__(self) -> None:
        if self.split not in SPLIT_CHOICES:
            raise EvaluationError(
                f"--split must be one of {', '.join(SPLIT_CHOICES)}, got {self.split!r}"
            )
        check_runtime(self.backend, self.precision)
        if isinstance(self.batch_size, bool) or not isinstance(self.batch_size, int):
            raise EvaluationError(f"--batch-size must be an integer, got {self.batch_size!r}")
        if self.batch_size < 1:
            raise EvaluationError(f"--batch-size must be >= 1, got {self.batch_size}")
        if self.max_frames is not None and (
            isinstance(self.max_frames, bool)
            or not isinstance(self.max_frames, int)
            or self.max_frames < 1
        ):
            raise EvaluationError(f"--max-frames must be >= 1, got {self.max_frames}")
        object.__setattr__(self, "device", str(self.device))  # a torch.device is named

    def to_dict(self) -> dict:
        return asdict(self)
