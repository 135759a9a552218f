"""The calibration's clock: one wall-clock budget for everything, evaluations included.

``calibrate --budget-min M`` must end within M + 10 %. Its :class:`Budget` starts when the
command starts (before torch is imported), and every stage asks it how much time is
left before it starts. What a stage will take is estimated from what the run has
measured so far: an evaluation of ``n`` frames costs at most what a measured one of
``m`` frames cost, times ``max(1, n / m)`` (an evaluation costs a fixed part plus a part
per frame, so this bound holds for any cost of that form), times :data:`SAFETY` for a
machine shared with other work. Stages that do not fit are left out or shortened
(fewer test frames, a shorter fine-tuning), never the budget extended; what was left
out is recorded and said.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator

SECONDS_PER_MIN = 60.0
SAFETY = 1.3  # estimates are multiplied by this (the load of a shared machine varies)
FIRST_EVAL_GUESS_S = (2.5, 0.06)  # before any measurement: fixed s + s per frame (a width-8
# model at 64 px on 2 shared cores)


class Budget:
    """``minutes`` of wall clock from ``started`` (``time.monotonic()``; default now)."""

    def __init__(self, minutes: float, started: float | None = None):
        self.started = time.monotonic() if started is None else started
        self.total_s = minutes * SECONDS_PER_MIN
        self.deadline = self.started + self.total_s
        self.evaluations: list[tuple[int, float]] = []  # (frames, seconds) measured
        self.spent: dict[str, float] = {}  # seconds per stage

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def left(self) -> float:
        """Seconds left before the deadline (negative when past it)."""
        return self.deadline - time.monotonic()

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the ``with`` block into ``spent[name]`` (added up over blocks)."""
        t0 = time.monotonic()
        try:
            yield
        finally:
            self.spent[name] = self.spent.get(name, 0.0) + time.monotonic() - t0

    def observe_evaluation(self, frames: int, seconds: float) -> None:
        self.evaluations.append((max(int(frames), 1), float(seconds)))

    def evaluation_s(self, frames: int) -> float:
        """The estimated upper bound of an evaluation of ``frames`` frames, seconds."""
        if frames <= 0:
            return 0.0
        if not self.evaluations:
            fixed, per_frame = FIRST_EVAL_GUESS_S
            return SAFETY * (fixed + per_frame * frames)
        return SAFETY * min(s * max(1.0, frames / m) for m, s in self.evaluations)

    def frames_within(self, seconds: float, most: int, evaluations: int = 1) -> int:
        """The most frames (<= ``most``) of which ``evaluations`` evaluations fit in
        ``seconds`` (0 if not even one frame does)."""
        if most <= 0 or evaluations <= 0 or self.evaluation_s(1) * evaluations > seconds:
            return 0
        low, high = 1, int(most)
        while low < high:  # evaluation_s is non-decreasing in frames
            mid = (low + high + 1) // 2
            if self.evaluation_s(mid) * evaluations <= seconds:
                low = mid
            else:
                high = mid - 1
        return low

    def record(self) -> dict:
        """What metrics.json says about the budget."""
        elapsed = self.elapsed()
        return {
            "budget_s": round(self.total_s, 1),
            "seconds": round(elapsed, 1),
            "stages_s": {k: round(v, 1) for k, v in self.spent.items()},
            "within_budget": elapsed <= self.total_s,
        }


def minutes(seconds: float) -> str:
    """``seconds`` as the help and the messages show a budget."""
    return f"{math.ceil(seconds / SECONDS_PER_MIN * 10) / 10:g} min"
