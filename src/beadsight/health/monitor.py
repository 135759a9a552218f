"""Sensor health: how far the sensor at rest has drifted from its rest reference.

Beads settle, LEDs age, the camera gets knocked, the model's zero creeps. Whenever the
pouch is at rest (no recent contact, still frames: :mod:`beadsight.health.watch`),
:class:`HealthMonitor` averages :attr:`HealthSettings.rest_frames` rest frames and
compares them with the :class:`~beadsight.health.rest.RestReference` (from calibration,
or taken automatically the first time the pouch is certainly unloaded):

=======================  =====================================================  =============
figure                   how                                                    drifting /
                                                                                recalibrate
=======================  =====================================================  =============
``bead_creep_mm``        OpenCV Farneback optical flow, reference -> now, at     0.3 / 0.8
                         64 px: 90th percentile of the flow minus its median
``camera_shift_mm``      the median of that flow (the whole image moved)        0.5 / 1.5
``brightness_change_pct``  mean brightness, now against the reference           10 / 30
``colour_change_pct``    largest change of a channel's share of the colour      5 / 15
``zero_offset_n``        force read at rest, now against the reference          0.1 / 0.3
=======================  =====================================================  =============

The state is the worst figure's: ``ok``, ``drifting`` (readings usable; plan a
recalibration) or ``recalibrate``; ``unknown`` before there is a reference. Each
:class:`HealthReport` says what to do. The work (about a millisecond at 64 px) runs on
rest frames only, at most every :attr:`HealthSettings.check_period_s` of frame time,
on a worker thread (``background=True``), so it never slows the sensing loop.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from beadsight.config import ConfigError
from beadsight.health.rest import REST_PX, RestAverage, RestReference

logger = logging.getLogger(__name__)

HEALTH_STATES = ("unknown", "ok", "drifting", "recalibrate")
FLOW_MARGIN_PX = 4  # flow this close to the image border is left out (px at REST_PX)
CREEP_PERCENTILE = 90  # bead creep: this percentile of the flow minus its median
_FLOW_CONTRAST = 40.0  # images are normalised to this standard deviation before flow
ADVICE = {  # what to do when a figure is past its "recalibrate" threshold
    "bead_creep_mm": "the beads have settled: take a new rest reference and recalibrate "
    "(beadsight health --save-rest, beadsight calibrate)",
    "camera_shift_mm": "the camera moved against the pouch: re-seat it, then recalibrate",
    "brightness_change_pct": "the lighting changed: check the LEDs and stray light",
    "colour_change_pct": "the light's colour changed: check the LEDs and stray light",
    "zero_offset_n": "the force read at rest moved: take a new rest reference (re-zero)",
}


@dataclass(frozen=True)
class HealthThresholds:
    """(drifting, recalibrate) thresholds of each figure."""

    bead_creep_mm: tuple[float, float] = (0.3, 0.8)
    camera_shift_mm: tuple[float, float] = (0.5, 1.5)
    brightness_change_pct: tuple[float, float] = (10.0, 30.0)
    colour_change_pct: tuple[float, float] = (5.0, 15.0)
    zero_offset_n: tuple[float, float] = (0.1, 0.3)

    def __post_init__(self) -> None:
        for name, pair in self.__dict__.items():
            if len(pair) != 2 or not 0 < pair[0] <= pair[1]:
                raise ConfigError(f"health threshold {name} must be 0 < drifting <= "
                                  f"recalibrate, got {pair!r}")  # fmt: skip


@dataclass(frozen=True)
class HealthSettings:
    """How health is tracked."""

    thresholds: HealthThresholds = field(default_factory=HealthThresholds)
    rest_frames: int = 15  # rest frames averaged per check (and for an automatic reference)
    check_period_s: float = 1.0  # at most one check per this much frame time, s
    zero_force_n: float = 0.05  # |force| below this at rest: certainly unloaded (auto reference)

    def __post_init__(self) -> None:
        if isinstance(self.rest_frames, bool) or int(self.rest_frames) < 1:
            raise ConfigError(f"health rest_frames must be >= 1, got {self.rest_frames!r}")
        for name in ("check_period_s", "zero_force_n"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not value > 0 or not math.isfinite(value):
                raise ConfigError(f"health {name} must be a number > 0, got {value!r}")


@dataclass(frozen=True)
class HealthReport:
    """state: one of :data:`HEALTH_STATES`; message: what it means and what to do;
    figures: name -> value (see the module docstring; ``rest_age_s``: frame time since
    the figures were measured); reference: "none", "file", "auto" or "given"."""

    state: str
    message: str
    figures: dict[str, float]
    reference: str
    checked_at_s: float = math.nan  # frame time of the check, s

    def summary(self) -> str:
        figures = ", ".join(f"{k} {v:.3g}" for k, v in self.figures.items())
        return f"{self.state}: {self.message}" + (f" ({figures})" if figures else "")


UNKNOWN = HealthReport(
    "unknown", "no rest reference yet: waiting for the pouch to be unloaded and still", {},
    "none",
)  # fmt: skip


def measure(reference: RestReference, now: RestReference, sensor_size_mm: float) -> dict:
    """The figures of ``now`` against ``reference`` (module docstring)."""
    flow = cv2.calcOpticalFlowFarneback(
        _normalised(reference.gray), _normalised(now.gray), None, 0.5, 3, 15, 3, 5, 1.1, 0
    )  # (REST_PX, REST_PX, 2) px, reference -> now
    m = FLOW_MARGIN_PX
    vectors = flow[m:-m, m:-m].reshape(-1, 2)
    median = np.median(vectors, axis=0)
    residual = np.linalg.norm(vectors - median, axis=1)
    mm_per_px = sensor_size_mm / REST_PX
    ref_share = reference.mean_rgb / max(reference.mean_rgb.sum(), 1e-6)
    now_share = now.mean_rgb / max(now.mean_rgb.sum(), 1e-6)
    return {
        "bead_creep_mm": float(np.percentile(residual, CREEP_PERCENTILE) * mm_per_px),
        "camera_shift_mm": float(np.linalg.norm(median) * mm_per_px),
        "brightness_change_pct": float(
            abs(now.mean_rgb.mean() / max(reference.mean_rgb.mean(), 1e-6) - 1) * 100
        ),
        "colour_change_pct": float(np.max(np.abs(now_share / ref_share - 1)) * 100),
        "zero_offset_n": float(abs(now.zero_force_n - reference.zero_force_n)),
    }


def _normalised(gray: np.ndarray) -> np.ndarray:
    """Zero-mean, fixed-contrast uint8 (optical flow then ignores brightness changes)."""
    g = gray.astype(np.float32)
    g = (g - g.mean()) * (_FLOW_CONTRAST / max(float(g.std()), 1e-3)) + 128.0
    return np.clip(g, 0, 255).astype(np.uint8)


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
        return "drifting", f"drifting: {names} past the drifting threshold; readings still " \
            "usable, plan a recalibration"  # fmt: skip
    return "ok", "at rest like the reference: nothing to do"


class HealthMonitor:
    """Health figures of rest frames against a rest reference (module docstring).

    sensor_size_mm: the side of the field of view of the frames (the model's geometry).
    reference: a :class:`RestReference` (calibration), or None to take one automatically.
    background: do the checks on a worker thread (live sensing) instead of in :meth:`add`.
    """

    def __init__(
        self,
        sensor_size_mm: float,
        settings: HealthSettings | None = None,
        reference: RestReference | None = None,
        background: bool = False,
    ):
        self.sensor_size_mm = float(sensor_size_mm)
        self.settings = settings or HealthSettings()
        self.reference = reference
        self._batch = RestAverage()
        self._last_check_s = -math.inf
        self._report = UNKNOWN
        self._lock = threading.Lock()
        self._pending: tuple[RestReference, float] | None = None
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self._thread: threading.Thread | None = None
        self.checks = 0
        if background:
            self._thread = threading.Thread(target=self._work, name="beadsight-health", daemon=True)
            self._thread.start()

    @property
    def report(self) -> HealthReport:
        return self._report

    def add(self, frame_rgb: np.ndarray, force_n: float, t_s: float, rest: bool) -> HealthReport:
        """One frame (``rest``: unloaded and still) with its force (N) at frame time ``t_s``;
        returns the newest report."""
        if not rest:
            self._batch.clear()
            return self._report
        if t_s - self._last_check_s < self.settings.check_period_s and self.reference:
            return self._report
        self._batch.add(frame_rgb, force_n)
        if self._batch.frames >= self.settings.rest_frames:
            now = self._batch.reference("auto")
            self._batch.clear()
            self._last_check_s = t_s
            if self._thread is None:
                self._check(now, t_s)
            else:
                with self._wake:
                    self._pending = (now, t_s)  # a newer batch replaces one not yet checked
                    self._wake.notify()
        return self._report

    def _check(self, now: RestReference, t_s: float) -> None:
        if self.reference is None:
            if abs(now.zero_force_n) >= self.settings.zero_force_n:
                return  # not certainly unloaded: no automatic reference from it
            self.reference = now
            logger.info("health: rest reference taken (%d frames)", now.frames)
        figures = measure(self.reference, now, self.sensor_size_mm)
        state, message = judge(figures, self.settings.thresholds)
        if state != self._report.state:
            log = logger.warning if state in ("drifting", "recalibrate") else logger.info
            log("health: %s", message)
        self.checks += 1
        self._report = HealthReport(state, message, figures, self.reference.origin, t_s)

    def _work(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._pending is not None or self._closed)
                if self._closed:
                    return
                job, self._pending = self._pending, None
            try:
                self._check(*job)
            except Exception:
                logger.exception("health: a check failed")

    def flush(self, timeout_s: float = 5.0) -> HealthReport:
        """Wait until a pending background check is done; the newest report."""
        with self._wake:
            self._wake.wait_for(lambda: self._pending is None, timeout_s)
        return self._report

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(5.0)
