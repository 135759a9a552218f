"""Sensor health: drift, the change of the rest state between two unloaded moments.

The sensor is seen at rest whenever a rest reference is taken
(:class:`~beadsight.health.rest.RestTracker`: unloaded and still, about once a second).
:class:`HealthMonitor` compares each new rest state with earlier ones. A press leaves
the beads in a new packing (in the simulator every press does: the rest states on either
side of one differ by 0.2-0.4 mm of local bead motion), and a rest-referenced model reads
against the new rest, so a press's new packing is not drift. Drift is what changes while
nothing touches the pouch, and what no press explains:

=========================  ==================================================  =============
figure                     how (rest images at 64 px, OpenCV Farneback flow)   drifting /
                                                                               recalibrate
=========================  ==================================================  =============
``bead_creep_mm``          the flow's affine deformation (a least-squares fit,  0.3 / 0.8
                           translation left out), as the displacement at half
                           the field of view: within the current unloaded
                           stretch, from its first rest state to now, plus the
                           earlier stretches' deformation where it was over
                           :data:`CREEP_STEP_MM` or took the creep past the
                           drifting threshold (the beads crept while nothing
                           touched them)
``camera_shift_mm``        the flow's median (the whole image moved): within    0.5 / 1.5
                           the current stretch, plus every earlier shift
                           between two rest states (within a stretch or across
                           a press) over :data:`SHIFT_STEP_MM`
``brightness_change_pct``  mean brightness against the first rest reference     10 / 30
                           (a rest file, else the one taken at start-up)
``colour_change_pct``      largest change of a channel's share of the colour,   5 / 15
                           against the same reference
=========================  ==================================================  =============

The steps keep measurement noise from adding up: over 10 minutes of the clean simulator
(3 seeds, about 90 presses each) an unloaded stretch's deformation was at most 0.053 mm
and a shift across a press at most 0.095 mm (``benchmarks/health_drift.py``). The state
is the worst figure's: ``ok``, ``drifting`` (readings usable; plan a recalibration) or
``recalibrate``; ``unknown`` before the first rest reference. Each
:class:`HealthReport` says what to do. The work (two flows at 64 px, a few
milliseconds) runs once per rest reference, on a worker thread (``background=True``),
so it never slows the sensing loop.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from beadsight.config import ConfigError
from beadsight.data.rest import RestReference
from beadsight.health.flow import bead_motion, rest_gray

logger = logging.getLogger(__name__)

HEALTH_STATES = ("unknown", "ok", "drifting", "recalibrate")
CREEP_STEP_MM = 0.1  # a finished unloaded stretch's deformation counts from this size, mm
SHIFT_STEP_MM = 0.2  # a shift between two rest states counts from this size, mm
ADVICE = {  # what to do when a figure is past its "recalibrate" threshold
    "bead_creep_mm": "the beads have settled: recalibrate (beadsight calibrate); the rest "
    "reference follows them by itself",
    "camera_shift_mm": "the camera moved against the pouch: re-seat it, then recalibrate",
    "brightness_change_pct": "the lighting changed: check the LEDs and stray light",
    "colour_change_pct": "the light's colour changed: check the LEDs and stray light",
}


@dataclass(frozen=True)
class HealthThresholds:
    """(drifting, recalibrate) thresholds of each figure."""

    bead_creep_mm: tuple[float, float] = (0.3, 0.8)
    camera_shift_mm: tuple[float, float] = (0.5, 1.5)
    brightness_change_pct: tuple[float, float] = (10.0, 30.0)
    colour_change_pct: tuple[float, float] = (5.0, 15.0)

    def __post_init__(self) -> None:
        for name, pair in self.__dict__.items():
            if len(pair) != 2 or not 0 < pair[0] <= pair[1]:
                raise ConfigError(
                    f"health threshold {name} must be 0 < drifting <= recalibrate, got {pair!r}"
                )


@dataclass(frozen=True)
class HealthSettings:
    """How health is tracked."""

    thresholds: HealthThresholds = field(default_factory=HealthThresholds)
    rest_refresh_s: float = 1.0  # at most one rest reference (and check) per this frame time

    def __post_init__(self) -> None:
        value = self.rest_refresh_s
        if not isinstance(value, (int, float)) or not value > 0 or not math.isfinite(value):
            raise ConfigError(f"health rest_refresh_s must be a number > 0, got {value!r}")


@dataclass(frozen=True)
class HealthReport:
    """state: one of :data:`HEALTH_STATES`; message: what it means and what to do;
    figures: name -> value (module docstring); reference: where the first rest reference
    came from ("none", "file", "start-up", "given"); checked_at_s: frame time of the
    rest state checked."""

    state: str
    message: str
    figures: dict[str, float]
    reference: str
    checked_at_s: float = math.nan

    def summary(self) -> str:
        figures = ", ".join(f"{k} {v:.3g}" for k, v in self.figures.items())
        return f"{self.state}: {self.message}" + (f" ({figures})" if figures else "")


UNKNOWN = HealthReport(
    "unknown", "no rest reference yet: waiting for the pouch to be unloaded and still", {}, "none"
)


@dataclass(frozen=True)
class _Seen:
    """A rest state as the figures need it: gray (:func:`rest_gray`), mean RGB."""

    gray: np.ndarray
    mean_rgb: np.ndarray

    @classmethod
    def of(cls, rest: RestReference) -> _Seen:
        return cls(rest_gray(rest.image), rest.image.reshape(-1, 3).mean(axis=0))


def deformation_mm(deformation: np.ndarray) -> float:
    """The largest displacement (mm) a (2, 2) deformation gives at half the field of view."""
    return float(np.linalg.svd(deformation, compute_uv=False)[0])


def appearance(reference: _Seen, now: _Seen) -> dict[str, float]:
    """Brightness and colour of ``now`` against ``reference``, %."""
    ref_share = reference.mean_rgb / max(reference.mean_rgb.sum(), 1e-6)
    now_share = now.mean_rgb / max(now.mean_rgb.sum(), 1e-6)
    brightness = abs(now.mean_rgb.mean() / max(reference.mean_rgb.mean(), 1e-6) - 1) * 100
    return {
        "brightness_change_pct": float(brightness),
        "colour_change_pct": float(np.max(np.abs(now_share / ref_share - 1)) * 100),
    }


def judge(figures: dict[str, float], thresholds: HealthThresholds) -> tuple[str, str]:
    """(state, message) of the figures: the worst figure decides."""
    over = {"drifting": [], "recalibrate": []}
    for name, value in figures.items():
        pair = getattr(thresholds, name, None)
        if pair is None:
            continue
        if value >= pair[1]:
            over["recalibrate"].append(name)
        elif value >= pair[0]:
            over["drifting"].append(name)
    if over["recalibrate"]:
        advice = "; ".join(ADVICE[n] for n in over["recalibrate"])
        return "recalibrate", f"recalibrate: {', '.join(over['recalibrate'])} too large: {advice}"
    if over["drifting"]:
        names = ", ".join(over["drifting"])
        return (
            "drifting",
            f"drifting: {names} past the drifting threshold; readings still usable, plan a "
            "recalibration",
        )
    return "ok", "at rest like the reference: nothing to do"


class DriftState:
    """The drift figures of a sequence of rest states (module docstring); not thread-safe.

    reference: a rest file's reference (the first state), or None (the first state added).
    creep_alarm_mm: the creep that raises the state (a finished stretch that took the creep
    past it is counted whatever its size, so the state does not fall back by bookkeeping).
    """

    def __init__(
        self,
        sensor_size_mm: float,
        reference: RestReference | None = None,
        creep_alarm_mm: float = HealthThresholds().bead_creep_mm[0],
    ):
        self.sensor_size_mm = float(sensor_size_mm)
        self.creep_alarm_mm = float(creep_alarm_mm)
        self.reference = reference
        self._anchor = _Seen.of(reference) if reference is not None else None
        self._start: _Seen | None = None  # first rest state of the current unloaded stretch
        self._last: _Seen | None = None  # the previous rest state
        self._deformation = np.zeros((2, 2))  # counted deformation of finished stretches
        self._shift = np.zeros(2)  # counted shifts, mm
        self._now = (np.zeros((2, 2)), np.zeros(2))  # the current stretch's, so far

    def add(self, rest: RestReference, loaded_before: bool) -> dict[str, float]:
        """A new rest state (``loaded_before``: the pouch was loaded since the previous
        one); returns the figures."""
        seen = _Seen.of(rest)
        if self._anchor is None:
            self.reference, self._anchor = rest, seen
        if self._start is None:
            loaded_before = True  # after a rest file: what happened since is unknown
            self._last = self._anchor
        if loaded_before:
            self._finish_stretch(seen)
        else:
            motion = bead_motion(self._start.gray, seen.gray, self.sensor_size_mm)
            self._now = motion.deformation, motion.shift
        self._last = seen
        deformation, shift = self._deformation + self._now[0], self._shift + self._now[1]
        return {
            "bead_creep_mm": deformation_mm(deformation),
            "camera_shift_mm": float(np.linalg.norm(shift)),
            **appearance(self._anchor, seen),
        }

    def _finish_stretch(self, seen: _Seen) -> None:
        """Count the finished stretch's deformation and shift where over their steps, and
        the shift across the load; ``seen`` starts a new stretch."""
        deformation, shift = self._now
        total = self._deformation + deformation
        if deformation_mm(deformation) >= CREEP_STEP_MM or (
            deformation_mm(total) >= self.creep_alarm_mm
        ):
            self._deformation = total
        if np.linalg.norm(shift) >= SHIFT_STEP_MM:
            self._shift += shift
        across = bead_motion(self._last.gray, seen.gray, self.sensor_size_mm).shift
        if np.linalg.norm(across) >= SHIFT_STEP_MM:
            self._shift += across
        self._start, self._now = seen, (np.zeros((2, 2)), np.zeros(2))


class HealthMonitor:
    """Health of the rest states of one sensor (module docstring).

    sensor_size_mm: the side of the field of view of the frames (the model's geometry).
    reference: a rest file's :class:`~beadsight.data.rest.RestReference`, or None (the
    first rest state taken). background: check on a worker thread instead of in
    :meth:`add`.
    """

    def __init__(
        self,
        sensor_size_mm: float,
        settings: HealthSettings | None = None,
        reference: RestReference | None = None,
        background: bool = False,
    ):
        self.settings = settings or HealthSettings()
        creep_alarm_mm = self.settings.thresholds.bead_creep_mm[0]
        self.drift = DriftState(sensor_size_mm, reference, creep_alarm_mm)
        self._report = UNKNOWN
        self._lock = threading.Lock()
        self._pending: tuple[RestReference, bool] | None = None
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self._busy = False  # the worker is checking a rest state
        self._thread: threading.Thread | None = None
        self.checks = 0
        if background:
            self._thread = threading.Thread(target=self._work, name="beadsight-health", daemon=True)
            self._thread.start()

    @property
    def report(self) -> HealthReport:
        return self._report

    @property
    def reference(self) -> RestReference | None:
        """The first rest reference, which brightness and colour are compared with."""
        return self.drift.reference

    def add(self, rest: RestReference, loaded_before: bool) -> HealthReport:
        """A new rest state (``loaded_before``: loaded since the previous one); returns the
        newest report (in the background: the one before this state is checked)."""
        if self._thread is None:
            self._check(rest, loaded_before)
            return self._report
        with self._wake:
            if self._pending is not None:  # not checked yet: the newer one replaces it
                loaded_before = loaded_before or self._pending[1]
            self._pending = (rest, loaded_before)
            self._wake.notify()
        return self._report

    def _check(self, rest: RestReference, loaded_before: bool) -> None:
        first = self.drift.reference is None
        figures = self.drift.add(rest, loaded_before)
        if first:
            logger.info("health: first rest reference (%s, %d frames)", rest.origin, rest.frames)
        state, message = judge(figures, self.settings.thresholds)
        if state != self._report.state:
            log = logger.warning if state in ("drifting", "recalibrate") else logger.info
            log("health: %s", message)
        self.checks += 1
        origin = self.drift.reference.origin
        self._report = HealthReport(state, message, figures, origin, rest.taken_at_s)

    def _work(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._pending is not None or self._closed)
                if self._closed:
                    return
                job, self._pending, self._busy = self._pending, None, True
            try:
                self._check(*job)
            except Exception:
                logger.exception("health: a check failed")
            with self._wake:
                self._busy = False
                self._wake.notify_all()

    def flush(self, timeout_s: float = 5.0) -> HealthReport:
        """Wait until the background checks are done; the newest report."""
        with self._wake:
            self._wake.wait_for(lambda: self._pending is None and not self._busy, timeout_s)
        return self._report

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(5.0)
