"""The clock of a training run: its wall-clock budget, timed validation, the progress bar.

With ``TrainConfig.budget_min`` the run stops once that much time has passed (training
and validation together, counted over resumes), at the end of the step under way; the
learning-rate schedule then spans the budget instead of the step count, and the progress
bar counts seconds of the budget, so it shows the time left. ``val_every_min`` adds a
validation (and a chance to keep ``best.pt``) at least that often, for runs whose epochs
are long compared with their budget.
"""

from __future__ import annotations

import time

from tqdm import tqdm

from beadsight.train.config import TrainConfig

SECONDS_PER_MIN = 60.0
BUDGET_BAR_FORMAT = (
    "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s budget [{remaining} left{postfix}]"
)


class Clock:
    """Elapsed time of a run (``elapsed_s`` carried over from the runs it resumes)."""

    def __init__(self, config: TrainConfig, elapsed_s: float = 0.0):
        self.limit_s = config.budget_min * SECONDS_PER_MIN if config.budget_min else None
        self.val_every_s = config.val_every_min * SECONDS_PER_MIN if config.val_every_min else None
        self.before_s = elapsed_s
        self.t0 = time.monotonic()
        self.last_val = self.t0
        self._shown = 0.0

    def elapsed(self) -> float:
        return self.before_s + time.monotonic() - self.t0

    def progress(self) -> float | None:
        """Share of the budget spent (0..1), or None without a budget."""
        return None if self.limit_s is None else min(self.elapsed() / self.limit_s, 1.0)

    def exhausted(self) -> bool:
        return self.limit_s is not None and self.elapsed() >= self.limit_s

    def validation_due(self) -> bool:
        """A timed validation is due (``val_every_min``); the caller then validates."""
        return self.val_every_s is not None and time.monotonic() - self.last_val >= self.val_every_s

    def validated(self) -> None:
        self.last_val = time.monotonic()

    def bar(self, step: int, total: int, disable: bool) -> tqdm:
        """Steps done of ``total``, or, with a budget, seconds of it (the time left)."""
        if self.limit_s is None:
            return tqdm(
                total=total,
                initial=step,
                desc="training",
                unit="step",
                mininterval=1.0,
                disable=disable,
            )
        self._shown = min(self.elapsed(), self.limit_s)
        return tqdm(
            total=self.limit_s,
            initial=self._shown,
            desc="training",
            unit="s",
            mininterval=1.0,
            bar_format=BUDGET_BAR_FORMAT,
            disable=disable,
        )

    def advance(self, bar: tqdm) -> None:
        """Move the bar by one step, or to the time spent."""
        if self.limit_s is None:
            bar.update(1)
            return
        now = min(self.elapsed(), self.limit_s)
        bar.update(now - self._shown)
        self._shown = now
