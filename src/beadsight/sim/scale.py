"""A simulated kitchen scale: an HX711 load-cell amplifier read by an Arduino.

What a real rig records is not the force on the finger but the scale's readings:
grams, at the HX711's output data rate (10 or 80 samples/s), each the average of
the load over its conversion period, with noise, a slowly wandering zero (tare
drift) and two-decimal printing. :class:`SimulatedScale` produces exactly that
from the simulator's true force.
"""

from __future__ import annotations

import math

import numpy as np

from beadsight.config import REFERENCE_G_TO_N
from beadsight.sim.config import SimConfig

_TIME_EPS_S = 1e-9  # sample times are compared with this tolerance


class SimulatedScale:
    """HX711-like scale. Feed it the true force; it answers with readings at its rate.

    ``sample(t_s, true_force_n)`` must be called with non-decreasing times (the
    simulator calls it at every physics step and at every sample time from
    :attr:`next_sample_s`). It integrates the force over time and, when a
    sample is due, returns the reading in grams (the average force over the
    conversion period, plus noise and tare drift, rounded to the resolution);
    otherwise ``None``. The scale is tared at its first sample time: a reading of
    an unloaded scale is 0 g plus noise and drift.
    """

    def __init__(self, config: SimConfig, seed: int | np.random.SeedSequence = 0):
        self.config = config
        self.period_s = 1.0 / config.scale_rate_hz
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        self._rng = np.random.default_rng(seq)
        self._phase_s = float(self._rng.uniform(0.0, self.period_s))
        self._next_t: float | None = None
        self._last_t: float | None = None
        self._last_f = 0.0
        self._integral = 0.0  # integral of force over the current conversion, N s
        self._span_s = 0.0
        self._drift_g = 0.0
        self._drift_t: float | None = None

    @property
    def next_sample_s(self) -> float | None:
        """Time of the next reading (None before the first call to :meth:`sample`)."""
        return self._next_t

    def sample(self, t_s: float, true_force_n: float) -> float | None:
        """Advance to ``t_s`` with load ``true_force_n`` (N). Returns grams, or None."""
        t_s = float(t_s)
        f = max(float(true_force_n), 0.0)
        if self._next_t is None:
            # Sample times are on a fixed grid with a random phase, as a free-running ADC.
            self._next_t = t_s + self._phase_s
            self._drift_t = t_s
        if self._last_t is not None:
            dt = t_s - self._last_t
            if dt < -_TIME_EPS_S:
                raise ValueError(
                    f"SimulatedScale.sample: time went backwards ({t_s} < {self._last_t})"
                )
            self._integral += 0.5 * (f + self._last_f) * max(dt, 0.0)
            self._span_s += max(dt, 0.0)
        self._last_t, self._last_f = t_s, f
        if t_s < self._next_t - _TIME_EPS_S:
            return None
        mean_f = self._integral / self._span_s if self._span_s > 0 else f
        self._integral, self._span_s = 0.0, 0.0
        while self._next_t <= t_s + _TIME_EPS_S:
            self._next_t += self.period_s
        return self._reading_g(t_s, mean_f)

    def _reading_g(self, t_s: float, force_n: float) -> float:
        cfg = self.config
        assert self._drift_t is not None
        dt = max(t_s - self._drift_t, 0.0)
        self._drift_t = t_s
        self._drift_g += cfg.scale_drift_g_per_sqrt_s * math.sqrt(dt) * self._rng.standard_normal()
        grams = force_n / REFERENCE_G_TO_N + self._drift_g
        grams += cfg.scale_noise_g * self._rng.standard_normal()
        return round(grams / cfg.scale_resolution_g) * cfg.scale_resolution_g

    @property
    def drift_g(self) -> float:
        """Current tare offset (grams): what the scale reads, noise aside, with no load."""
        return self._drift_g
