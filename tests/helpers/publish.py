"""Shared pieces of the ROS 2 and Foxglove tests: updates that carry a health state (as a
sensor that tracks drift gives them, issue 15 item 3) and a camera at its frame rate."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace

from beadsight.cli import main
from beadsight.live.listeners import LiveUpdate
from helpers.live import ScriptedSource

HEALTH_STATES = ("ok", "drifting", "recalibrate")


@dataclass(frozen=True)
class Health:
    """A health state with its figures (the interface of ``LiveUpdate.health``)."""

    state: str
    figures: dict
    message: str = ""


class HealthTagger:
    """A listener in front of a publisher that gives each update a health state: ok, then
    drifting, then recalibrate (a third of ``total`` updates each), with figures."""

    def __init__(self, target, total: int):
        self.target, self.total, self.count = target, total, 0

    def push(self, update: LiveUpdate) -> None:
        state = HEALTH_STATES[min(3 * self.count // self.total, 2)]
        figures = {"bead_shift_px": 0.5 * self.count, "force_offset_n": float("nan"), "n": 3}
        health = Health(state, figures, f"{state}: see docs/live.md")
        self.target.push(replace(update, health=health))
        self.count += 1

    def status(self, status) -> None:
        self.target.status(status)

    def finish(self) -> None:
        self.target.finish()


class PacedSource(ScriptedSource):
    """The scripted camera at its frame rate (so that nothing queues up anywhere)."""

    def async_read(self, timeout_s=None, max_frames=None):
        time.sleep(1 / self.fps)
        return super().async_read(timeout_s, max_frames)


def live_without(monkeypatch, capsys, module: str, *args: str) -> list[str]:
    """``beadsight live --no-viewer ARGS`` in this process as if ``module`` were not
    installed (``None`` in ``sys.modules`` is what an absent package looks like to
    ``import``, for it and each of its loaded modules); returns its stderr lines (it must
    exit 1). In a child process the same check spent 3 s importing torch."""
    for name in [m for m in sys.modules if m.split(".")[0] == module] + [module]:
        monkeypatch.setitem(sys.modules, name, None)
    capsys.readouterr()
    assert main(["live", "--no-viewer", *args]) == 1
    return capsys.readouterr().err.strip().splitlines()
