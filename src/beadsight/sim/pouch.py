"""Bead mechanics: a pouch of hydrogel beads and air bubbles in water, pressed by a flat finger.

The model is kinematic and physically motivated rather than a particle simulation:

* **Resting arrangement.** Beads (and, behind them, bubbles) lie in a single layer
  inside the pouch at "home" positions: random, relaxed so they overlap little.
  The homes drift slowly (a random walk) and each bead jitters about its place.
* **Response to the finger.** A finger at depth ``d`` below the pouch surface
  compresses the beads under it once the water layer's slack is taken up
  (vertical strain ``(d - slack) / diameter``, so they flatten and look larger) and pushes beads outward: the displacement grows linearly from
  the finger's centre to its rim and decays exponentially beyond it, scaled by
  ``d``, by a per-bead, per-press random gain and by the bead's distance from the
  pouch wall (beads against the wall cannot move away). Neighbours that overlap
  push each other apart.
* **Viscous lag and hysteresis.** Beads follow their targets with a first-order
  lag (water is viscous), faster outward than back. When the finger leaves, the
  beads do not return home: each settles at a new place (part of its peak
  displacement plus random settling), so every press leaves a new arrangement.
* **Force.** The pouch stiffens nonlinearly: ``F_eq = k F_ref (d / d_ref)^p``, with
  ``k`` larger near the walls and where beads are packed more densely under the
  finger, and a random per-press factor no camera can see. A viscoelastic branch
  (standard linear solid) adds force while loading and relaxes during the dwell,
  so the peak comes at the end of the descent and the force sags while the finger
  holds still.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from beadsight.sim.config import SimConfig

_WALL_CLEARANCE = 0.6  # bead centres stay this fraction of their radius inside the wall
_MIN_MOBILITY = 0.12  # mobility of a bead pressed against the wall
_MAX_PACKING_FACTOR = 1.35  # clamp of the local-packing stiffness factor
_MIN_PACKING_FACTOR = 0.7
_INIT_RELAX_ITERS = 300  # overlap relaxation of the initial arrangement
_SETTLE_RELAX_ITERS = 12  # overlap relaxation after a press
_SETTLE_REACH_MM = 9.0  # re-settling noise decays with this distance beyond the finger rim
_GLOBAL_SETTLE_FRACTION = 0.08  # far from the press, beads still re-settle this much
_MOVING_MM = 0.02  # beads further than this from home are still moving: relax overlaps


@dataclass(frozen=True)
class PouchView:
    """What the camera sees of the pouch at one instant (draw order, back to front).

    xy_mm: (K, 2) float64 centres, mm from the sensor centre (printer frame);
    radius_mm: (K,) apparent radius (compressed beads look larger);
    flatness: (K,) 0..1 (1 = compressed by ``max_compression``);
    tint: (K,) int index into ``config.bead_tints_rgb``, or -1 for an air bubble;
    index: (K,) int which bead or bubble each entry is (the same object keeps its index).
    """

    xy_mm: np.ndarray
    radius_mm: np.ndarray
    flatness: np.ndarray
    tint: np.ndarray
    index: np.ndarray


def relax_overlaps(
    xy: np.ndarray, radius: np.ndarray, min_fraction: float, limit: np.ndarray, iters: int
) -> np.ndarray:
    """Push apart discs closer than ``min_fraction * (r_i + r_j)``; keep centres within +-limit.

    xy: (K, 2) mm (a relaxed copy is returned); radius: (K,) mm; limit: (K,) mm per
    disc. Each iteration moves both discs of every overlapping pair half the overlap
    apart (neighbour pairs from a k-d tree), then clamps to the walls.
    """
    xy = np.clip(xy, -limit[:, None], limit[:, None])
    k = len(xy)
    if k < 2:
        return xy
    reach = min_fraction * 2 * float(radius.max())
    for _ in range(iters):
        pairs = cKDTree(xy).query_pairs(reach, output_type="ndarray")
        if len(pairs) == 0:
            break
        i, j = pairs[:, 0], pairs[:, 1]
        d = xy[i] - xy[j]
        dist = np.sqrt((d * d).sum(1))
        overlap = min_fraction * (radius[i] + radius[j]) - dist
        hit = overlap > 0
        if not hit.any():
            break
        i, j, d, dist, overlap = i[hit], j[hit], d[hit], dist[hit], overlap[hit]
        push = d * (0.5 * overlap / np.maximum(dist, 1e-9))[:, None]
        for axis in (0, 1):
            xy[:, axis] += np.bincount(i, push[:, axis], k) - np.bincount(j, push[:, axis], k)
        np.clip(xy, -limit[:, None], limit[:, None], out=xy)
    return xy


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class BeadPouch:
    """The mechanical state of one pouch. Advance it with :meth:`step`.

    rng: the generator all mechanical randomness is drawn from (arrangement,
    jitter, settling, per-press factors). Rendering uses its own generator, so
    rendering at any size, or not at all, leaves the mechanics unchanged.
    """

    def __init__(self, config: SimConfig, rng: np.random.Generator):
        self.config = config
        self.rng = rng
        cfg = config
        n, m = cfg.n_beads, cfg.n_bubbles
        self.n_beads, self.n_bubbles = n, m
        diam = rng.normal(cfg.bead_diameter_mm, cfg.bead_diameter_spread_mm, n)
        diam = np.clip(diam, 0.6 * cfg.bead_diameter_mm, 1.4 * cfg.bead_diameter_mm)
        lo, hi = cfg.bubble_diameter_range_mm
        self.radius_mm = np.concatenate([diam, rng.uniform(lo, hi, m)]) / 2  # (K,)
        self.is_bubble = np.arange(n + m) >= n
        self.tint = np.where(self.is_bubble, -1, rng.integers(0, len(cfg.bead_tints_rgb), n + m))
        self.layer = rng.random(n + m)  # fixed draw order at rest
        self.limit_mm = cfg.pouch_half_mm - _WALL_CLEARANCE * self.radius_mm
        spread = cfg.bead_lag_spread
        self.lag_out_s = cfg.bead_lag_s * rng.lognormal(0.0, spread, n + m)
        self.lag_back_s = cfg.bead_return_lag_s * rng.lognormal(0.0, spread, n + m)
        bubble = self.is_bubble
        self.lag_out_s[bubble] /= cfg.bubble_mobility
        self.lag_back_s[bubble] /= cfg.bubble_mobility
        self.home = self._initial_arrangement()
        self.pos = self.home.copy()  # lagged positions (no jitter), mm
        self.jitter = rng.normal(0.0, cfg.jitter_mm, (n + m, 2))
        self.strain = np.zeros(n + m)  # lagged vertical strain (compression)
        self.time_s = 0.0
        # Contact state.
        self.in_contact = False
        self.press_gain = np.ones(n + m)
        self.press_stiffness = 1.0
        self.peak_depth_mm = 0.0
        self.peak_disp = np.zeros((n + m, 2))
        self.finger_xy_mm = np.zeros(2)
        self.depth_mm = 0.0
        # Force state (viscoelastic branch).
        self._f_eq = 0.0
        self._f_relax = 0.0
        self.force_n = 0.0
        self.presses_completed = 0

    # --- arrangement ----------------------------------------------------------------
    def _initial_arrangement(self) -> np.ndarray:
        k = len(self.radius_mm)
        xy = self.rng.uniform(-1.0, 1.0, (k, 2)) * self.limit_mm[:, None]
        return self._relax(xy, _INIT_RELAX_ITERS)

    def _relax(self, xy: np.ndarray, iters: int) -> np.ndarray:
        """Relax beads among beads and bubbles among bubbles (bubbles float behind beads)."""
        out = xy.copy()
        frac = self.config.min_spacing_fraction
        for group in (~self.is_bubble, self.is_bubble):
            if group.any():
                out[group] = relax_overlaps(
                    xy[group], self.radius_mm[group], frac, self.limit_mm[group], iters
                )
        return out

    # --- mechanics ------------------------------------------------------------------
    def mobility(self, xy: np.ndarray) -> np.ndarray:
        """(K,) 0..1: beads near the pouch wall move less (the wall holds them)."""
        gap = self.config.pouch_half_mm - np.abs(xy).max(axis=1) - self.radius_mm
        mob = np.clip(gap / self.config.edge_margin_mm, _MIN_MOBILITY, 1.0)
        return np.where(self.is_bubble, mob * self.config.bubble_mobility, mob)

    def stiffness_factor(self, finger_xy_mm: np.ndarray) -> float:
        """Position-dependent stiffness: the finger near the wall presses a stiffer pouch."""
        cfg = self.config
        reach = float(np.abs(finger_xy_mm).max()) + cfg.finger_radius_mm
        edge_zone = (reach - (cfg.pouch_half_mm - cfg.edge_margin_mm)) / cfg.edge_margin_mm
        return 1.0 + cfg.edge_stiffening * float(np.clip(edge_zone, 0.0, 1.0))

    def packing_factor(self, finger_xy_mm: np.ndarray) -> float:
        """Stiffness factor from how densely beads are packed under the finger (visible)."""
        cfg = self.config
        beads = ~self.is_bubble
        r = self.radius_mm[beads]
        rho = np.linalg.norm(self.home[beads] - finger_xy_mm, axis=1)
        overlap = np.clip((cfg.finger_radius_mm + r - rho) / (2 * r), 0.0, 1.0)
        coverage = float((overlap * math.pi * r * r).sum()) / (math.pi * cfg.finger_radius_mm**2)
        mean_coverage = float((math.pi * r * r).sum()) / cfg.pouch_size_mm**2
        factor = 1.0 + cfg.packing_stiffness_gain * (coverage / max(mean_coverage, 1e-6) - 1.0)
        return float(np.clip(factor, _MIN_PACKING_FACTOR, _MAX_PACKING_FACTOR))

    def _begin_contact(self, finger_xy_mm: np.ndarray) -> None:
        cfg = self.config
        self.in_contact = True
        self.peak_depth_mm = 0.0
        self.peak_disp[:] = 0.0
        self.press_gain = self.rng.lognormal(0.0, cfg.push_gain_spread, len(self.radius_mm))
        hidden = self.rng.lognormal(0.0, cfg.press_stiffness_spread)
        self.press_stiffness = self.packing_factor(finger_xy_mm) * hidden

    def _end_contact(self) -> None:
        """The finger left: every bead settles somewhere new (stochastic settling, hysteresis)."""
        cfg = self.config
        rho = np.linalg.norm(self.home - self.finger_xy_mm, axis=1)
        reach = np.exp(-np.maximum(rho - cfg.finger_radius_mm, 0.0) / _SETTLE_REACH_MM)
        reach = _GLOBAL_SETTLE_FRACTION + (1 - _GLOBAL_SETTLE_FRACTION) * reach
        sigma = cfg.settle_noise_mm_per_mm * self.peak_depth_mm * reach
        mob = np.minimum(self.mobility(self.home), 1.0)
        noise = self.rng.standard_normal(self.home.shape) * (sigma * mob)[:, None]
        new_home = self.home + cfg.hysteresis_fraction * self.peak_disp + noise
        self.home = self._relax(new_home, _SETTLE_RELAX_ITERS)
        self.in_contact = False
        self.presses_completed += 1

    def _force(self, dt_s: float, finger_xy_mm: np.ndarray, depth_mm: float) -> float:
        cfg = self.config
        if depth_mm > 0:
            k = self.stiffness_factor(finger_xy_mm) * self.press_stiffness
            f_eq = k * cfg.equilibrium_force_n(depth_mm)
        else:
            f_eq = 0.0
        decay = math.exp(-dt_s / cfg.relaxation_time_s)
        self._f_relax = self._f_relax * decay + cfg.relaxation_fraction * (f_eq - self._f_eq)
        self._f_eq = f_eq
        return max(f_eq + self._f_relax, 0.0) if depth_mm > 0 else 0.0

    def _targets(self, finger_xy_mm: np.ndarray, depth_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Where each bead is pushed (mm) and its vertical strain, for the finger as it is now."""
        cfg = self.config
        if depth_mm <= 0:
            return self.home, np.zeros(len(self.home))
        u = self.home - finger_xy_mm
        rho = np.sqrt((u * u).sum(1))
        direction = u / np.maximum(rho, 1e-6)[:, None]
        r_f = cfg.finger_radius_mm
        profile = np.where(rho < r_f, rho / r_f, np.exp(-(rho - r_f) / cfg.push_decay_mm))
        amount = cfg.push_gain_mm_per_mm * depth_mm * profile * self.press_gain
        amount *= self.mobility(self.home)
        target = self.home + direction * amount[:, None]
        target = np.clip(target, -self.limit_mm[:, None], self.limit_mm[:, None])
        # The membrane presses beads under the finger; it bends back over a short rim.
        press = 1.0 - _smoothstep((rho - r_f) / cfg.membrane_falloff_mm)
        diameter = 2 * self.radius_mm
        squeeze = max(depth_mm - cfg.pouch_slack_mm, 0.0)  # first the water gives way
        strain = np.clip(squeeze * press / diameter, 0.0, cfg.max_compression)
        return target, strain

    def step(self, dt_s: float, finger_xy_mm, depth_mm: float) -> float:
        """Advance ``dt_s`` seconds with the finger at ``finger_xy_mm`` (mm from centre)
        and ``depth_mm`` below the pouch surface (<= 0: not touching). Returns the
        true normal force on the finger (N)."""
        if not dt_s > 0:
            raise ValueError(f"step: dt_s must be > 0, got {dt_s}")
        cfg = self.config
        xy = np.asarray(finger_xy_mm, dtype=np.float64).reshape(2)
        depth = float(depth_mm)
        if depth > 0 and not self.in_contact:
            self._begin_contact(xy)
        self.finger_xy_mm, self.depth_mm = xy, depth
        self.force_n = self._force(dt_s, xy, depth)

        target, strain = self._targets(xy, depth)
        # Viscous lag: faster while loading (moving away from home) than on the way back.
        loading = ((target - self.home) ** 2).sum(1) >= ((self.pos - self.home) ** 2).sum(1)
        tau = np.where(loading, self.lag_out_s, self.lag_back_s)
        alpha = 1.0 - np.exp(-dt_s / tau)
        self.pos += (target - self.pos) * alpha[:, None]
        tau_c = np.where(strain >= self.strain, self.lag_out_s, self.lag_back_s)
        self.strain += (strain - self.strain) * (1.0 - np.exp(-dt_s / tau_c))
        if depth > 0 or float(np.abs(self.pos - self.home).max()) > _MOVING_MM:
            # Displaced beads push their neighbours (bubbles slip past one another).
            beads = ~self.is_bubble
            self.pos[beads] = relax_overlaps(
                self.pos[beads],
                self.radius_mm[beads],
                cfg.min_spacing_fraction,
                self.limit_mm[beads],
                1,
            )

        # Jitter (Ornstein-Uhlenbeck) and slow drift of the resting arrangement.
        e = math.exp(-dt_s / cfg.jitter_time_s)
        amp = cfg.jitter_mm * math.sqrt(1 - e * e)
        scale = np.where(self.is_bubble, cfg.bubble_mobility, 1.0)[:, None]
        self.jitter = self.jitter * e + amp * scale * self.rng.standard_normal(self.jitter.shape)
        if cfg.drift_mm_per_sqrt_s > 0:
            walk = cfg.drift_mm_per_sqrt_s * math.sqrt(dt_s)
            self.home = np.clip(
                self.home + walk * self.rng.standard_normal(self.home.shape),
                -self.limit_mm[:, None],
                self.limit_mm[:, None],
            )

        if self.in_contact and depth >= self.peak_depth_mm - 1e-9:
            self.peak_depth_mm = depth
            self.peak_disp = self.pos - self.home
        if depth <= 0 and self.in_contact:
            self._end_contact()
        self.time_s += dt_s
        return self.force_n

    # --- what the camera sees ---------------------------------------------------------
    def view(self) -> PouchView:
        """The visible state, bubbles first (they float behind the beads), then beads
        ordered so that compressed beads (against the window) are drawn last."""
        xy = np.clip(
            self.pos + self.jitter,
            -self.config.pouch_half_mm,
            self.config.pouch_half_mm,
        )
        strain = self.strain
        radius = self.radius_mm / np.sqrt(1.0 - strain)  # volume-conserving flattening
        order = np.argsort(self.layer + 2.0 * strain - 10.0 * self.is_bubble, kind="stable")
        return PouchView(
            xy_mm=xy[order],
            radius_mm=radius[order],
            flatness=(strain / self.config.max_compression)[order],
            tint=self.tint[order],
            index=order,
        )

    @property
    def displacement_mm(self) -> np.ndarray:
        """(K,) distance of each bead/bubble from its resting place (mm, lagged, no jitter)."""
        return np.linalg.norm(self.pos - self.home, axis=1)
