"""The run folder of a training run, and the checkpoints in it (only rank 0 writes)::

    config.json    the resolved TrainConfig
    split.json     press ids per split, split fractions/seed, dataset path + fingerprint
    metrics.jsonl  one JSON object per log event (same keys on every line)
    last.pt        newest checkpoint with the full training state (resume from it)
    best.pt        lowest validation loss (model + metadata only)

Every file but ``metrics.jsonl`` is replaced atomically (:mod:`beadsight.files`): a
full disk, a kill or Ctrl-C leaves the previous version under the final name and
raises :class:`~beadsight.files.WriteError`. Hidden ``.NAME.*.tmp`` files a killed
run left behind are removed when a run starts or resumes and before every save.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from beadsight.checkpoint import CheckpointError, PressureModel
from beadsight.config import ConfigError
from beadsight.files import (
    OutputExistsError,
    atomic_write_text,
    os_errors_as_write_errors,
    remove_stale_temps,
)
from beadsight.train.config import CONFIG_FILE

logger = logging.getLogger(__name__)

SPLIT_FILE, METRICS_FILE = "split.json", "metrics.jsonl"
LAST_CHECKPOINT, BEST_CHECKPOINT = "last.pt", "best.pt"
RUN_FILES = (CONFIG_FILE, SPLIT_FILE, METRICS_FILE, LAST_CHECKPOINT, BEST_CHECKPOINT)
METRIC_KEYS = (
    "event",
    "step",
    "epoch",
    "train_loss",
    "val_loss",
    "val_mae_kpa",
    "samples_per_s",
    "threads",  # CPU threads of the steps (train/threads.py)
    "lr",
    "time_s",
    "wall_time",
)


class RunFolder:
    """Paths and writers of a run folder."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @property
    def last(self) -> Path:
        return self.path / LAST_CHECKPOINT

    @property
    def best(self) -> Path:
        return self.path / BEST_CHECKPOINT

    def check(self, resume: bool) -> None:
        """Refuse to resume without ``last.pt``, or to start over a run that has one."""
        if self.path.exists() and not self.path.is_dir():
            raise OutputExistsError(f"{self.path}: is a file; expected a run folder (--out)")
        if resume and not self.last.is_file():
            raise CheckpointError(
                f"{self.last}: no checkpoint to resume from (out={self.path}); "
                "start without --resume"
            )
        if not resume and self.last.is_file():
            raise ConfigError(
                f"out {self.path} already holds a training run ({LAST_CHECKPOINT}); pass "
                "--resume to continue it, or choose another --out"
            )

    def remove_stale_temps(self) -> list[Path]:
        """Remove the temporary files an interrupted write of a run file left behind."""
        removed = [p for name in RUN_FILES for p in remove_stale_temps(self.path, name)]
        for path in removed:
            logger.info("removed %s (left by an interrupted write)", path)
        return removed

    def write_json(self, name: str, obj: Any) -> None:
        atomic_write_text(self.path / name, json.dumps(obj, indent=2, sort_keys=True) + "\n")

    def log(self, **values: Any) -> dict[str, Any]:
        """Append one metrics line (every key of METRIC_KEYS; missing ones are null)."""
        line = {key: values.get(key) for key in METRIC_KEYS}
        path = self.path / METRICS_FILE
        with os_errors_as_write_errors(path), path.open("a") as f:
            f.write(json.dumps(line) + "\n")
        return line

    def truncate_metrics(self, step: int) -> None:
        """Drop events after ``step`` (written after the checkpoint a resume starts from)."""
        path = self.path / METRICS_FILE
        if not path.is_file():
            return
        kept = []
        for text in path.read_text().splitlines():
            try:
                line = json.loads(text)
            except json.JSONDecodeError:  # a line cut short by a kill or a full disk
                continue
            if isinstance(line, dict) and (line.get("step") or 0) <= step:
                kept.append(json.dumps(line))
        atomic_write_text(path, "".join(k + "\n" for k in kept))

    def save_checkpoints(self, model: PressureModel, best: bool, **state: Any) -> None:
        """Write ``last.pt`` with the training ``state`` and, if ``best``, ``best.pt``
        (model and metadata only). Raises WriteError; the previous files stay intact."""
        self.remove_stale_temps()
        model.save(self.last, **state)
        if best:
            model.save(self.best, step=state.get("step"))
