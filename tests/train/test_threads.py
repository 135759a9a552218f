"""The CPU thread tuner keeps the thread count whose steps are faster, and times again later."""

from __future__ import annotations

import pytest
import torch
from helpers.train import one_torch_thread  # noqa: F401

from beadsight.train.threads import ThreadTuner, training_threads


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def run_steps(tuner: ThreadTuner, clock: FakeClock, n: int, cost: dict[int, float]) -> list[int]:
    """``n`` steps, each taking ``cost[threads it ran at]`` seconds; the counts they ran at."""
    seen = []
    for _ in range(n):
        with tuner.timed():
            seen.append(torch.get_num_threads())
            clock.now += cost[torch.get_num_threads()]
    return seen


@pytest.mark.parametrize("faster", [1, 2])
def test_tuner_keeps_the_faster_count_and_probes_again(faster):
    clock = FakeClock()
    tuner = ThreadTuner([2, 1], probe_steps=3, reprobe_s=60.0, clock=clock)
    cost = {faster: 0.5, 3 - faster: 2.0}
    seen = run_steps(tuner, clock, 8, cost)
    assert seen == [2] * 4 + [1] * 4  # one untimed and 3 timed steps at each
    assert tuner.chosen == faster and torch.get_num_threads() == faster
    assert tuner.history == [{"step_s": {2: cost[2], 1: cost[1]}, "threads": faster}]
    # until reprobe_s has passed, every step runs at the faster count
    assert run_steps(tuner, clock, 10, cost) == [faster] * 10
    clock.now += 60.0
    # then the load changed: the other count is faster now
    cost = {faster: 3.0, 3 - faster: 1.0}
    seen = run_steps(tuner, clock, 40, cost)
    assert seen[:8] == [2] * 4 + [1] * 4
    assert tuner.chosen == 3 - faster and set(seen[8:]) == {3 - faster}
    assert len(tuner.history) == 2
    tuner.restore()
    assert torch.get_num_threads() == 1  # the helpers' fixture's count before the tuner


def test_fixed_threads_are_never_changed():
    clock = FakeClock()
    tuner = ThreadTuner([1], clock=clock)
    assert run_steps(tuner, clock, 10, {1: 1.0, 2: 1.0}) == [1] * 10 and tuner.history == []


def test_training_threads_tunes_only_single_process_cpu_runs():
    torch.set_num_threads(2)
    assert training_threads(None, torch.device("cpu"), 1).choices == [2, 1]
    assert training_threads(3, torch.device("cpu"), 1).choices == [3]
    assert torch.get_num_threads() == 3
    assert training_threads(None, torch.device("cpu"), 2).choices == [3]  # DDP: unchanged
    torch.set_num_threads(1)
    assert training_threads(None, torch.device("cpu"), 1).choices == [1]
    with pytest.raises(ValueError, match="thread counts"):
        ThreadTuner([0])
