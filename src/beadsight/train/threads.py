"""The CPU threads of a training run: fixed (``TrainConfig.threads``), or chosen by timing.

torch's intra-op threads wait for each other at every operation by spinning. On a machine
whose cores are also busy with other work, a thread that lost its core holds the others
up, and a step can take several times longer at torch's default thread count than at one
thread (``benchmarks/train_speed.py --variants main t1+main``: 2.4 against 8.6 samples/s
at 64 px, width 16, on a 2-core CPU under a load of ~7). On an idle machine more threads
should be faster. So with ``threads`` unset, a CPU run times its own steps: a few at each
candidate count (torch's default, and 1), keeps the faster, and times them again every
:data:`REPROBE_S`, as the machine's load changes. The probing steps are ordinary training
steps: each probe runs :data:`PROBE_STEPS` + 1 of them at every candidate count, so about
that many steps in each :data:`REPROBE_S` run at the slower count.
"""

from __future__ import annotations

import contextlib
import logging
import statistics
import time
from collections.abc import Callable, Iterator

import torch

logger = logging.getLogger(__name__)

PROBE_STEPS = 3  # timed steps per candidate thread count (after one untimed step)
REPROBE_S = 120.0  # time the candidates again this often (seconds)


class ThreadTuner:
    """Chooses torch's intra-op thread count among ``choices`` by the time of the steps.

    Call :meth:`step_started` before each training step and :meth:`step_ended` after it;
    the tuner sets ``torch.set_num_threads`` itself. ``clock``: seconds, monotonic.
    """

    def __init__(
        self,
        choices: list[int],
        probe_steps: int = PROBE_STEPS,
        reprobe_s: float = REPROBE_S,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not choices or any(c < 1 for c in choices):
            raise ValueError(f"thread counts must be >= 1, got {choices}")
        self.choices = list(dict.fromkeys(choices))
        self.initial = torch.get_num_threads()  # restored by restore()
        self.probe_steps, self.reprobe_s, self.clock = probe_steps, reprobe_s, clock
        self.chosen = self.choices[0]
        self.times: dict[int, list[float]] = {}
        self.history: list[dict] = []  # each probe's median step seconds per count
        self._queue: list[int] = []
        self._skip = False
        self._t0 = 0.0
        self._chosen_at = -float("inf")
        self._probe()

    @property
    def threads(self) -> int:
        """The count the next step runs at."""
        return self._queue[0] if self._queue else self.chosen

    def _probe(self) -> None:
        self._queue = list(self.choices) if len(self.choices) > 1 else []
        self.times = {c: [] for c in self._queue}
        self._skip = True
        torch.set_num_threads(self.threads)

    def restore(self) -> None:
        """Set torch's thread count back to what it was before this tuner."""
        torch.set_num_threads(self.initial)

    @contextlib.contextmanager
    def timed(self) -> Iterator[None]:
        """Time the ``with`` block as one step."""
        self.step_started()
        yield
        self.step_ended()

    def step_started(self) -> None:
        if len(self.choices) > 1 and not self._queue:
            if self.clock() - self._chosen_at >= self.reprobe_s:
                self._probe()
        self._t0 = self.clock()

    def step_ended(self) -> None:
        if not self._queue:
            return
        seconds = self.clock() - self._t0
        if self._skip:  # the first step at a new count pays for starting its threads
            self._skip = False
            return
        count = self._queue[0]
        self.times[count].append(seconds)
        if len(self.times[count]) < self.probe_steps:
            return
        self._queue.pop(0)
        self._skip = True
        if not self._queue:
            self._choose()
        torch.set_num_threads(self.threads)

    def _choose(self) -> None:
        medians = {c: statistics.median(t) for c, t in self.times.items()}
        self.chosen = min(medians, key=lambda c: (medians[c], -c))
        self._chosen_at = self.clock()
        self.history.append({"step_s": medians, "threads": self.chosen})
        logger.info(
            "CPU threads: %d (median step %s)",
            self.chosen,
            ", ".join(f"{s:.3f} s at {c}" for c, s in medians.items()),
        )


def training_threads(threads: int | None, device: torch.device, world: int) -> ThreadTuner:
    """The tuner of a run's threads: ``threads`` if given; else, for a single-process CPU run
    on more than one thread, the faster of torch's default and 1; else torch's default."""
    default = torch.get_num_threads()
    if threads:
        return ThreadTuner([threads])
    if torch.device(device).type == "cpu" and world == 1 and default > 1:
        return ThreadTuner([default, 1])
    return ThreadTuner([default])
