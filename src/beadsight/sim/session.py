"""A simulated data-collection session: the printer presses, the scale reads, the camera films.

:class:`SimulatedSession` runs the reference press pattern against a
:class:`~beadsight.sim.simulator.PouchSimulator` and a
:class:`~beadsight.sim.scale.SimulatedScale` on one simulated clock and yields one
:class:`SimFrame` per camera frame. It is what ``beadsight simulate`` records, and
an endless session (``presses=None``) is a stand-in camera for the live viewer.

Physics is advanced to every camera frame time and to every scale sample time,
so the scale's readings are taken at their own instants (a free-running HX711)
rather than at frame times.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from beadsight.config import REFERENCE_G_TO_N
from beadsight.errors import ConfigError
from beadsight.sim.config import SimConfig
from beadsight.sim.looks import LookDraws, LookSample
from beadsight.sim.press import PROFILES, Press, PressCycle, check_profile, draw_profile
from beadsight.sim.scale import SimulatedScale
from beadsight.sim.simulator import PouchSimulator
from beadsight.sim.variety import PouchDistribution, PouchSample

_MIN_STEP_S = 1e-6  # physics steps shorter than this are skipped
_JITTER_CLIP = 3.0  # frame-time jitter is clipped at this many sigma


@dataclass(frozen=True)
class SimFrame:
    """One camera frame of a simulated session and what the rig knew at that instant.

    frame_rgb: (S, S, 3) uint8 RGB sensor-space frame (None if rendering is off);
    raw_bgr: (1024, 1280, 3) uint8 BGR raw fisheye frame (None unless asked for);
    timestamp_s: unix time of the frame on the simulated clock;
    true_force_n: the true normal force on the finger (N) - never stored in datasets;
    scale_force_n: the latest scale reading in N (what a live rig sees; NaN before the
    first reading); scale_readings: ((t_s, grams), ...) readings since the previous frame;
    commanded_xy_mm: (2,) the press position the printer was last commanded to, mm
    from the sensor centre; finger_xy_mm: (2,) where the finger actually is;
    finger_z_mm: printer Z; finger_depth_mm: depth below the pouch surface (<= 0: not
    touching); press_index: 0-based press cycle; phase: travel/descend/dwell/rise/pause;
    pouch_index: which pouch is in the sensor (0-based; see ``presses_per_pouch``).
    """

    frame_rgb: np.ndarray | None
    timestamp_s: float
    true_force_n: float
    scale_force_n: float
    commanded_xy_mm: np.ndarray
    finger_xy_mm: np.ndarray
    finger_z_mm: float
    finger_depth_mm: float
    press_index: int
    phase: str
    frame_index: int
    pouch_index: int = 0
    scale_readings: tuple[tuple[float, float], ...] = ()
    raw_bgr: np.ndarray | None = None


class SimulatedSession:
    """Iterate over the camera frames of a simulated calibration session.

    config: the simulated sensor and rig (default :class:`SimConfig`); seed: int;
    presses: None for an endless session, an int for that many random presses, or a
    sequence of :class:`Press` (each carries its own profile). profile: how drawn presses
    move, one of :data:`~beadsight.sim.press.PROFILES`: ``"reference"`` (the reference
    pattern) or ``"mixed"`` (long holds, slow ramps, depth changes while held; see
    :func:`~beadsight.sim.press.draw_profile`). A mixed session's presses are at the same
    places and bottom depths as the reference session with the same seed. render: render
    sensor-space frames (off: physics and scale only, much faster); raw: also
    render raw fisheye frames. presses_per_pouch: replace the pouch with a fresh one
    (new beads, arrangement, bubbles and look) before every this many presses, as a
    user swaps the $0.09 pouches (None: one pouch for the whole session).
    variety: ``"train"`` or ``"heldout"``: every pouch is a different *build*, drawn
    from that split of :class:`~beadsight.sim.variety.PouchDistribution` with
    ``config`` as its base (bead count, light, camera and image vary; rig, scale and
    timing stay ``config``'s); None: every pouch is ``config``. The same seed gives
    the same session; a finite session's presses are the first presses of the
    endless one with that seed. looks: ``"train"``, ``"heldout"`` or one family of
    :mod:`beadsight.sim.looks`: every pouch draws a family (uniformly) and its
    parameters, applied on top of its config or build; None: the reference look.
    """

    def __init__(
        self,
        config: SimConfig | None = None,
        seed: int = 0,
        presses: int | Sequence[Press] | None = None,
        *,
        render: bool = True,
        raw: bool = False,
        presses_per_pouch: int | None = None,
        variety: str | None = None,
        profile: str = "reference",
        looks: str | None = None,
    ):
        self.config = config if config is not None else SimConfig()
        self.seed = seed
        # A sixth stream for variety, a seventh for profiles, an eighth for looks: the first
        # five are those of sessions without them (SeedSequence children do not depend on
        # how many are spawned).
        streams = np.random.SeedSequence(seed).spawn(8)
        sim_seq, scale_seq, plan_seq, clock_seq, self._pouch_seq, variety_seq = streams[:6]
        self.profile = check_profile(profile)
        self._profile_rng = np.random.default_rng(streams[6])
        self.looks = looks
        self._looks = None if looks is None else LookDraws(looks, streams[7])
        self.variety = variety
        self._builds: list[PouchSample] = []
        if variety is not None:
            self._distribution = PouchDistribution(self.config)
            self._variety_rng = np.random.default_rng(variety_seq)
            self.pouch_build(0)  # checks the split
        self.simulator = PouchSimulator(self.pouch_config(0), sim_seq)
        if presses_per_pouch is not None and (
            isinstance(presses_per_pouch, bool) or int(presses_per_pouch) < 1
        ):
            raise ConfigError(f"presses_per_pouch must be >= 1 or None, got {presses_per_pouch!r}")
        self.presses_per_pouch = presses_per_pouch
        self.pouch_index = 0
        self.scale = SimulatedScale(self.config, scale_seq)
        self._plan_rng = np.random.default_rng(plan_seq)
        self._clock_rng = np.random.default_rng(clock_seq)
        self.render = render
        self.raw = raw
        if presses is None:
            self.presses: list[Press] | None = None
        elif isinstance(presses, (int, np.integer)):
            if presses < 0:
                raise ConfigError(f"presses must be >= 0, got {presses}")
            self.presses = [self._draw_press() for _ in range(int(presses))]
        else:
            if profile != PROFILES[0]:
                raise ConfigError(
                    f"profile={profile!r} is for drawn presses; a sequence of Press carries "
                    "its own profile (pass profile='reference')"
                )
            self.presses = list(presses)
        self._started = False

    # --- the pouches ----------------------------------------------------------------------
    def pouch_build(self, index: int) -> PouchSample:
        """The build drawn for pouch ``index`` (0-based) of a ``variety`` session."""
        if self.variety is None:
            raise ConfigError("pouch_build: this session has no variety (every pouch is config)")
        while len(self._builds) <= index:  # drawn in order, so the same for every caller
            self._builds.append(self._distribution.sample(self._variety_rng, self.variety))
        return self._builds[index]

    def pouch_look(self, index: int) -> LookSample:
        """The look drawn for pouch ``index`` of a ``looks`` session, applied to its build."""
        if self._looks is None:
            raise ConfigError("pouch_look: this session has no looks (every pouch is config's)")
        base = self.config if self.variety is None else self.pouch_build(index).config
        return self._looks.get(index, base)

    def pouch_config(self, index: int) -> SimConfig:
        """The simulated sensor of pouch ``index``: ``config``, or its drawn build, with
        its drawn look on top (``looks``)."""
        if self._looks is not None:
            return self.pouch_look(index).config
        return self.config if self.variety is None else self.pouch_build(index).config

    # --- the plan -----------------------------------------------------------------------
    def _draw_press(self) -> Press:
        cfg, rng = self.config, self._plan_rng
        x, y = rng.uniform(-cfg.press_range_mm, cfg.press_range_mm, 2)
        z = rng.uniform(*cfg.press_z_range_mm)
        return draw_profile(
            cfg, Press(float(x), float(y), float(z)), self.profile, self._profile_rng
        )

    def _cycles(self) -> Iterator[PressCycle]:
        start_s, xy, index = 0.0, np.zeros(2), 0
        while self.presses is None or index < len(self.presses):
            press = self._draw_press() if self.presses is None else self.presses[index]
            cycle = PressCycle(self.config, press, start_s, xy, index)
            yield cycle
            start_s, xy, index = cycle.end_s, press.xy_mm, index + 1

    @property
    def num_presses(self) -> int | None:
        return None if self.presses is None else len(self.presses)

    def duration_s(self) -> float | None:
        """Length of a finite session in seconds (None if endless)."""
        if self.presses is None:
            return None
        end = 0.0
        xy = np.zeros(2)
        for i, press in enumerate(self.presses):
            end = PressCycle(self.config, press, end, xy, i).end_s
            xy = press.xy_mm
        return end

    def num_frames(self) -> int | None:
        """Number of frames a finite session yields (None if endless)."""
        duration = self.duration_s()
        return None if duration is None else int(math.floor(duration * self.config.fps)) + 1

    # --- running ------------------------------------------------------------------------
    def __iter__(self) -> Iterator[SimFrame]:
        if self._started:
            raise RuntimeError("a SimulatedSession can be iterated once; make a new one")
        self._started = True
        return self._run()

    def _advance(self, cycle: PressCycle, t_now: float, t_to: float) -> tuple[float, list]:
        """Step physics from ``t_now`` to ``t_to`` (relative s), sampling the scale on the way."""
        readings = []
        start = self.config.start_time_s
        while True:
            next_sample = self.scale.next_sample_s
            t_next = t_to
            if next_sample is not None and next_sample - start < t_to:
                t_next = max(next_sample - start, t_now)
            if t_next - t_now > _MIN_STEP_S:
                xy, z, _ = cycle.state_at(t_next)
                self.simulator.step(t_next - t_now, xy, self.config.surface_z_mm - z)
            # A gap too short to step is still crossed: a sample due in it must be taken,
            # or the scale would never be ready and this loop would never end.
            t_now = t_next
            grams = self.scale.sample(start + t_now, self.simulator.force_n)
            if grams is not None:
                readings.append((start + t_now, grams))
            if t_now >= t_to - _MIN_STEP_S:
                return t_now, readings

    def _maybe_new_pouch(self, press_index: int) -> None:
        """Swap in a fresh pouch before every ``presses_per_pouch``-th press."""
        n = self.presses_per_pouch
        if n is not None and press_index > 0 and press_index % n == 0:
            (seq,) = self._pouch_seq.spawn(1)
            self.pouch_index += 1
            self.simulator = PouchSimulator(self.pouch_config(self.pouch_index), seq)

    def _run(self) -> Iterator[SimFrame]:
        cfg = self.config
        period = 1.0 / cfg.fps
        start = cfg.start_time_s
        end_s = self.duration_s()  # None: endless
        cycles = self._cycles()
        cycle = next(cycles, None)
        if cycle is None:
            return
        t_now = 0.0
        self.scale.sample(start, 0.0)  # the scale's clock starts with the session
        last_grams = math.nan
        pending: list[tuple[float, float]] = []
        frame_index = 0
        while end_s is None or frame_index * period <= end_s:
            jitter = cfg.frame_time_jitter_s * float(
                np.clip(self._clock_rng.standard_normal(), -_JITTER_CLIP, _JITTER_CLIP)
            )
            t_frame = max(frame_index * period + jitter, t_now)
            while t_frame > cycle.end_s:
                if t_now < cycle.end_s:
                    t_now, readings = self._advance(cycle, t_now, cycle.end_s)
                    pending += readings
                following = next(cycles, None)
                if following is None:
                    break  # the last cycle holds its final state
                cycle = following
                self._maybe_new_pouch(cycle.index)
            t_now, readings = self._advance(cycle, t_now, t_frame)
            pending += readings
            if pending:
                last_grams = pending[-1][1]
            xy, z, phase = cycle.state_at(t_now)
            sim = self.simulator
            yield SimFrame(
                frame_rgb=sim.render() if self.render else None,
                timestamp_s=start + t_now,
                true_force_n=sim.force_n,
                scale_force_n=last_grams * REFERENCE_G_TO_N,
                commanded_xy_mm=cycle.commanded_xy_mm,
                finger_xy_mm=xy,
                finger_z_mm=z,
                finger_depth_mm=cfg.surface_z_mm - z,
                press_index=cycle.index,
                phase=phase,
                frame_index=frame_index,
                pouch_index=self.pouch_index,
                scale_readings=tuple(pending),
                raw_bgr=sim.render_raw() if self.raw else None,
            )
            pending = []
            frame_index += 1
