"""The virtual printer's motion: planned straight moves in simulated time.

Each planned move is a segment run at constant speed (its feed rate, no acceleration),
starting when the previous one ends. Enough for the virtual printer to answer ``M114``
with an interpolated position and to know when ``M400`` may answer.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass
class Segment:
    """A straight move from ``p0`` at ``t0`` to ``p1`` at ``t1`` (simulated s, mm)."""

    t0: float
    t1: float
    p0: Vec3
    p1: Vec3

    def at(self, t: float) -> Vec3:
        if t >= self.t1 or self.t1 <= self.t0:
            return self.p1
        if t <= self.t0:
            return self.p0
        frac = (t - self.t0) / (self.t1 - self.t0)
        return tuple(a + frac * (b - a) for a, b in zip(self.p0, self.p1, strict=True))  # type: ignore[return-value]


class MotionPlan:
    """Planned segments after a rest position; not thread-safe (the printer locks)."""

    def __init__(self, rest: Vec3):
        self.rest: Vec3 = tuple(float(v) for v in rest)  # type: ignore[assignment]
        self.segments: deque[Segment] = deque()

    def position_at(self, t: float) -> Vec3:
        """The head position (x, y, z) mm at simulated time ``t``."""
        for seg in self.segments:
            if t < seg.t1:
                return seg.at(t)
        return self.last_point()

    def last_point(self) -> Vec3:
        """Where the planned motion ends."""
        return self.segments[-1].p1 if self.segments else self.rest

    def end(self) -> float:
        """Simulated time the planned motion ends (-inf when nothing was planned)."""
        return self.segments[-1].t1 if self.segments else -math.inf

    def pending(self, now: float) -> int:
        """Planned moves not finished at ``now`` (planner blocks in use)."""
        return sum(1 for s in self.segments if s.t1 > now)

    def add(self, now: float, target: Vec3, feed_mm_min: float) -> float:
        """Plan a move to ``target`` at ``feed_mm_min``; returns when it will end."""
        t0 = max(now, self.end())
        p0 = self.last_point()
        duration = math.dist(p0, target) / max(feed_mm_min, 1e-6) * 60.0
        self.segments.append(Segment(t0, t0 + duration, p0, tuple(target)))  # type: ignore[arg-type]
        return t0 + duration

    def prune(self, now: float) -> None:
        """Forget segments finished before ``now`` (keeping the last one)."""
        while len(self.segments) > 1 and self.segments[0].t1 <= now:
            self.segments.popleft()

    def stop(self, now: float, at: Vec3 | None = None) -> None:
        """Drop every planned move; the head rests where it is at ``now`` (or at ``at``)."""
        self.rest = self.position_at(now) if at is None else at
        self.segments.clear()
