"""The models a calibration chooses between, and how a fine-tuning one is trained in its time.

* ``zero-shot``: the base model as it came (the baseline; chosen only if nothing beats it);
* ``zero-press``: the base model with the new pouch's rest statistics (no press used;
  :func:`beadsight.calibrate.align.align_to_rest`);
* ``decoder`` / ``all``: the base fine-tuned (encoder fixed / every layer), from whichever
  of the two above has the lower MAE on the early-stopping presses;
* ``scratch``: a small model (:data:`~beadsight.calibrate.config.SCRATCH_WIDTH`) trained
  from scratch on the same presses.

:func:`train_candidate` runs the trainer so that the run, its setup and its last
validation included, ends by a given time: the trainer's clock counts the setup it
measured as time already spent (the mechanism a resumed run uses), and the run's own
budget leaves room for the last validation and save.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.calibrate.budget import Budget
from beadsight.calibrate.config import (
    CALIBRATION_SPLIT,
    SCRATCH_LR,
    SCRATCH_WIDTH,
    TRAIN_FOLDER,
    CalibrateConfig,
)
from beadsight.checkpoint import PressureModel
from beadsight.train.config import TrainConfig

logger = logging.getLogger(__name__)

SECONDS_PER_MIN = 60.0
RUN_EPOCHS = 1_000_000  # the time, not the epoch count, ends a fine-tuning
SAVE_RESERVE_S = 2.0  # saving best.pt / last.pt at the end of a fine-tuning
METRIC_KEYS = (
    "mae_kpa",
    "force_error_pct",
    "cop_error_mm",
    "iou",
    "worst_region_mae_kpa",
    "frames",
    "presses",
    "coverage",
    "window_coverage",
)


def figures(metrics: dict) -> dict:
    """The figures metrics.json keeps of an evaluation."""
    return {k: metrics.get(k) for k in METRIC_KEYS}


@dataclass
class Candidate:
    """One model a calibration may keep, and what happened to it."""

    name: str
    model: PressureModel | None = None
    status: str = "planned"  # "scored", or "skipped: <why>"
    start: str | None = None  # the candidate fine-tuning started from
    budget_s: float = 0.0  # the training time it was given
    seconds: float = 0.0  # the time it took (training and its scoring)
    steps: int = 0  # optimizer steps
    best_step: int | None = None  # the step of the kept checkpoint (0: the start)
    val: dict | None = None  # figures on the early-stopping presses (used to choose)
    test: dict | None = None  # figures on the test presses (never used to choose)
    notes: list[str] = field(default_factory=list)

    def skip(self, why: str) -> Candidate:
        self.status = f"skipped: {why}"
        logger.info("candidate %s %s", self.name, self.status)
        return self

    def record(self) -> dict:
        return {
            "status": self.status,
            "start": self.start,
            "budget_s": round(self.budget_s, 1),
            "seconds": round(self.seconds, 1),
            "steps": self.steps,
            "best_step": self.best_step,
            "val": self.val,
            "test": self.test,
            "notes": self.notes,
            "run_folder": f"{TRAIN_FOLDER}/{self.name}" if self.steps or self.best_step else None,
        }


def candidate_config(
    name: str, config: CalibrateConfig, base: PressureModel, start: Path, out: Path
) -> TrainConfig:
    """The TrainConfig of fine-tuning candidate ``name``: the base model's input shape
    (frames, stride, rest input, size), this run's presses and split; ``decoder``/``all``
    start from ``start`` with the calibration's recipe, ``scratch`` is a new width-
    :data:`SCRATCH_WIDTH` model at :data:`SCRATCH_LR` without dropout."""
    m = base.meta.model
    scratch = name == "scratch"
    return TrainConfig(
        data=str(config.data),
        out=str(out / TRAIN_FOLDER / name),
        init=None if scratch else str(start),
        frames=m.frames,
        frame_stride=m.frame_stride,
        width=SCRATCH_WIDTH if scratch else m.width,
        up_kernel=m.up_kernel,
        dropout=0.0 if scratch else m.dropout,
        rest_input=m.rest_input,
        rest_norm=m.rest_norm,
        image_size=base.image_size,
        epochs=RUN_EPOCHS,
        budget_min=1.0,  # set by train_candidate
        val_every_min=config.val_every_min,
        lr=max(SCRATCH_LR, config.lr) if scratch else config.lr,
        lr_min=config.lr_min,
        lr_schedule="cosine",
        batch_size=config.batch_size,
        noise_std=config.noise_std,
        augment=config.augment,
        split=CALIBRATION_SPLIT,
        seed=config.seed,
        presses=config.presses,
        skip_presses=config.skip,
        train_layers="decoder" if name == "decoder" else "all",
        device=config.device,
        progress=config.progress,
        log_every_steps=10,
        val_at_start=False,  # the start is a candidate of its own (zero-shot / zero-press)
        checkpoint_every_min=1e6,
    )


def train_candidate(tc: TrainConfig, until: float, end_reserve_s: float) -> tuple[Path, dict]:
    """Train as ``tc`` says so that the run ends by ``until`` (``time.monotonic()``):
    its loop stops ``end_reserve_s`` + :data:`SAVE_RESERVE_S` before, for the last
    validation and save. Returns (best checkpoint or None if the setup took all the
    time, {"steps", "best_step", "setup_s"})."""
    from beadsight.train.distributed import Distributed, resolve_device
    from beadsight.train.run import BEST_CHECKPOINT
    from beadsight.train.trainer import Trainer

    t0 = time.monotonic()
    run_s = until - t0 - end_reserve_s - SAVE_RESERVE_S
    tc = dataclasses.replace(tc, budget_min=max(run_s, 1e-3) / SECONDS_PER_MIN)
    device = resolve_device(tc.device, tc.precision)
    dist = Distributed.start(device)
    trainer = Trainer(tc, dist, device)
    try:
        trainer.setup()
        setup_s = time.monotonic() - t0
        trainer.elapsed_s = setup_s  # the setup counts against the run's budget
        trainer.loop()
    finally:
        trainer.close()
        dist.close()
    best = Path(tc.out) / BEST_CHECKPOINT
    info = {"steps": trainer.step, "best_step": trainer.best.get("step"), "setup_s": setup_s}
    return (best if best.is_file() else None), info


def timed_evaluate(
    budget: Budget,
    model: PressureModel | Path,
    config: CalibrateConfig,
    presses: np.ndarray,
    frames: int,
    **kwargs: Any,
) -> dict:
    """evaluate() of ``model`` on ``presses`` of ``config.data`` (at most ``frames``
    frames, spread evenly), timed into the budget's evaluation estimate. ``out_dir``,
    ``train_presses``, ``plots`` and ``report`` go to evaluate()."""
    from beadsight.evaluation.config import EvaluateConfig
    from beadsight.evaluation.evaluate import evaluate

    settings = EvaluateConfig(
        device=config.device,
        max_frames=frames,
        plots=kwargs.pop("plots", False),
        report=kwargs.pop("report", True),
        resize=True,
        progress=config.progress,
    )
    t0 = time.monotonic()
    metrics = evaluate(
        model, config.data, settings, kwargs.pop("out_dir", None), presses=presses, **kwargs
    )
    budget.observe_evaluation(int(metrics.get("frames") or frames), time.monotonic() - t0)
    return metrics
