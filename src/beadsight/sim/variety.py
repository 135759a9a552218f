"""The range of real builds: a seeded distribution over simulated sensors.

Every BeadSight is built by hand, and every build differs: how many beads went into
the pouch and how big and coloured they are, how many bubbles stayed in, how stiff
the filled pouch is; how bright, warm and well placed the LEDs are; how the camera
sits, which fisheye it has, how it is exposed and focused; how noisy and compressed
its frames are. A base model meant for *any* pouch must be trained over that range,
and tested on builds it never saw.

:class:`PouchDistribution` draws one build as a :class:`PouchSample`: a value for
every :class:`Factor` in :data:`FACTORS` and the :class:`SimConfig` they make.
Splits:

* ``"train"``: every factor uniform over its training range;
* ``"heldout"``: the factors with a held-out range (bead count, LED colour
  temperature, LED intensity) uniform over that range instead, which never
  overlaps the training range; all other factors as in training.

Sampling is seeded and reproducible: every draw uses the same number of random
numbers in the same order, whatever the split, so the ``i``-th held-out build of a
seed differs from the ``i``-th training build only in the held-out factors.
``docs/simulator.md`` lists every factor and its ranges.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from beadsight.errors import ConfigError
from beadsight.sim.config import MIXED_TINTS_RGB, SimConfig
from beadsight.sim.optics.light import colour_temperature_rgb

SPLITS = ("train", "heldout")
GROUPS = ("pouch", "light", "camera", "image")

# Tints a bag of water beads can hold (linear RGB multipliers): the reference pouch's
# mixed tints and three more; a build uses a few.
BEAD_PALETTE_RGB = (
    *MIXED_TINTS_RGB,
    (1.00, 0.66, 0.60),  # red
    (0.62, 0.95, 0.98),  # cyan
    (0.98, 0.98, 0.62),  # yellow
)
REFERENCE_BEADS = 100  # the bead count the stiffness law's reference force belongs to
BUBBLE_MIN_DIAMETER_MM = 0.6  # smallest bubble of every build


@dataclass(frozen=True)
class Factor:
    """One way builds differ: a name, its group, its unit and its ranges.

    train: (low, high) of the training split. heldout: (low, high) ranges of the
    held-out split; empty: the held-out split draws from ``train`` too. integer:
    values are integers, ranges inclusive at both ends.
    """

    name: str
    group: str
    unit: str
    train: tuple[float, float]
    heldout: tuple[tuple[float, float], ...] = ()
    integer: bool = False
    doc: str = ""

    def ranges(self, split: str) -> tuple[tuple[float, float], ...]:
        """The ranges values of ``split`` are drawn from (uniformly over their union)."""
        return self.heldout if split == "heldout" and self.heldout else (self.train,)

    def value(self, u: float, split: str) -> float:
        """The value at quantile ``u`` (0..1) of ``split``'s distribution of this factor."""
        ranges = self.ranges(split)
        widths = [hi - lo + (1 if self.integer else 0) for lo, hi in ranges]
        x = u * sum(widths)
        k = 0
        while k < len(ranges) - 1 and x >= widths[k]:
            x -= widths[k]
            k += 1
        lo, hi = ranges[k]
        if self.integer:
            return float(min(lo + math.floor(x), hi))
        return float(min(lo + x, hi))


def _f(name, group, unit, train, doc, heldout=(), integer=False) -> Factor:
    return Factor(name, group, unit, train, heldout, integer, doc)


FACTORS: tuple[Factor, ...] = (
    # --- the pouch ---------------------------------------------------------------
    _f(
        "n_beads",
        "pouch",
        "beads",
        (71, 129),
        "beads in the pouch",
        heldout=((60, 70), (130, 140)),
        integer=True,
    ),
    _f("bead_diameter_mm", "pouch", "mm", (3.5, 4.5), "mean diameter of a saturated bead"),
    _f("bead_diameter_spread_mm", "pouch", "mm", (0.15, 0.55), "std of bead diameters"),
    _f("tint_count", "pouch", "tints", (1, 6), "bead colours in the bag (from 9)", integer=True),
    _f("tint_strength", "pouch", "x", (0.4, 1.4), "saturation of the tints (1: reference)"),
    _f("n_bubbles", "pouch", "bubbles", (0, 12), "air bubbles left in", integer=True),
    _f("bubble_max_diameter_mm", "pouch", "mm", (1.2, 3.0), "largest bubble (smallest 0.6 mm)"),
    _f(
        "stiffness_scale",
        "pouch",
        "x",
        (0.8, 1.25),
        "pouch stiffness vs. the reference law (4.3 N at 1 mm for 100 beads, x sqrt(beads / 100))",
    ),
    _f("stiffness_exponent", "pouch", "", (2.0, 2.5), "F ~ depth^p: how fast the pouch stiffens"),
    # --- the light ---------------------------------------------------------------
    _f(
        "led_intensity",
        "light",
        "x",
        (0.75, 1.25),
        "LED brightness (1: reference build)",
        heldout=((0.55, 0.72), (1.28, 1.45)),
    ),
    _f(
        "led_colour_temperature_k",
        "light",
        "K",
        (3300, 5800),
        "LED colour temperature",
        heldout=((2800, 3200), (5900, 7000)),
    ),
    _f("vignetting", "light", "", (0.25, 0.6), "brightness lost at the image corners"),
    _f("led_offset_mm", "light", "mm", (12.0, 18.0), "LEDs at (+-this, +-this) from the centre"),
    _f("led_height_mm", "light", "mm", (8.0, 14.0), "distance of the LEDs from the beads"),
    _f("led_rotation_deg", "light", "deg", (-12.0, 12.0), "the LED square turned about the axis"),
    _f("ambient_light", "light", "", (0.12, 0.35), "light scattered in the housing"),
    # --- the camera --------------------------------------------------------------
    _f("exposure_gain", "camera", "x", (0.8, 1.2), "exposure x gain (1: reference build)"),
    _f("white_balance_red", "camera", "x", (0.88, 1.12), "red gain of the white balance"),
    _f("white_balance_blue", "camera", "x", (0.88, 1.12), "blue gain of the white balance"),
    _f("camera_tilt_rows_deg", "camera", "deg", (-2.5, 2.5), "tilt: keystone along the rows"),
    _f("camera_tilt_cols_deg", "camera", "deg", (-2.5, 2.5), "tilt: keystone along the columns"),
    _f("camera_roll_deg", "camera", "deg", (-3.0, 3.0), "rotation about the optical axis"),
    _f("camera_offset_x_mm", "camera", "mm", (-0.6, 0.6), "camera off the sensor centre, X"),
    _f("camera_offset_y_mm", "camera", "mm", (-0.6, 0.6), "camera off the sensor centre, Y"),
    _f("lens_focal_error", "camera", "", (-0.04, 0.04), "fisheye focal length vs. the reference"),
    _f("lens_distortion_k", "camera", "", (-0.05, 0.05), "fisheye law f theta (1 + k theta^2)"),
    _f("crop_scale_error", "camera", "", (-0.03, 0.03), "preprocessing crop too large (+)"),
    _f("crop_offset_x_mm", "camera", "mm", (-0.4, 0.4), "crop off the optical axis, X"),
    _f("crop_offset_y_mm", "camera", "mm", (-0.4, 0.4), "crop off the optical axis, Y"),
    # --- the image ---------------------------------------------------------------
    _f("noise_std", "image", "DN", (0.5, 4.5), "sensor noise, RMS, 0..255 units"),
    _f("flicker", "image", "", (0.0, 0.015), "RMS frame-to-frame brightness fluctuation"),
    _f("motion_blur_fraction", "image", "", (0.0, 0.4), "exposure reaching into the last frame"),
    _f("defocus_sigma_mm", "image", "mm", (0.0, 0.25), "out-of-focus blur on the pouch"),
    _f("jpeg_quality", "image", "", (50, 95), "MJPG (JPEG) quality of every frame", integer=True),
)
FACTOR_NAMES = tuple(f.name for f in FACTORS)


@dataclass(frozen=True)
class PouchSample:
    """One simulated build: the split it was drawn from, its factors and its config."""

    split: str
    factors: dict[str, float]
    config: SimConfig

    def to_dict(self) -> dict[str, Any]:
        return {"split": self.split, "factors": dict(self.factors)}


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise ConfigError(f"variety split must be one of {SPLITS}, got {split!r}")


class PouchDistribution:
    """A seeded distribution over builds: ``sample(rng, split)`` -> :class:`PouchSample`.

    base: the config every sample starts from; its rig, scale, timing and image size
    are kept (only the fields the factors set change). factors: the factors drawn.
    """

    def __init__(self, base: SimConfig | None = None, factors: tuple[Factor, ...] = FACTORS):
        names = [f.name for f in factors]
        unknown = sorted(set(names) - set(FACTOR_NAMES))
        if unknown or len(set(names)) != len(names):
            raise ConfigError(f"factors must be distinct names from FACTORS, got {names}")
        self.base = base if base is not None else SimConfig()
        self.factors = tuple(factors)

    def sample(self, rng: np.random.Generator, split: str = "train") -> PouchSample:
        """Draw one build. Uses ``len(FACTORS) + len(BEAD_PALETTE_RGB)`` uniforms of ``rng``."""
        _check_split(split)
        u = rng.random(len(FACTORS))
        palette_order = rng.permutation(len(BEAD_PALETTE_RGB))
        drawn = {f.name: f for f in self.factors}
        values = {
            f.name: drawn[f.name].value(float(q), split)
            for f, q in zip(FACTORS, u, strict=True)
            if f.name in drawn
        }
        config = build_config(values, self.base, palette_order)
        return PouchSample(split, values, config)


def sample_pouch(
    rng: np.random.Generator, split: str = "train", base: SimConfig | None = None
) -> PouchSample:
    """One build from the full distribution (:data:`FACTORS`); see :class:`PouchDistribution`."""
    return PouchDistribution(base).sample(rng, split)


def build_config(
    values: dict[str, float], base: SimConfig, palette_order: np.ndarray | None = None
) -> SimConfig:
    """``base`` with the factors in ``values`` applied (factors not given keep ``base``'s).

    palette_order: which palette tints a ``tint_count`` picks (default: the first ones).
    """
    v = values
    changes: dict[str, Any] = {}
    direct = (
        "bead_diameter_mm",
        "bead_diameter_spread_mm",
        "stiffness_exponent",
        "led_intensity",
        "vignetting",
        "led_offset_mm",
        "led_height_mm",
        "led_rotation_deg",
        "ambient_light",
        "exposure_gain",
        "camera_roll_deg",
        "lens_focal_error",
        "lens_distortion_k",
        "crop_scale_error",
        "noise_std",
        "flicker",
        "motion_blur_fraction",
        "defocus_sigma_mm",
    )
    changes.update({name: float(v[name]) for name in direct if name in v})
    for name in ("n_beads", "n_bubbles", "jpeg_quality"):
        if name in v:
            changes[name] = int(v[name])
    beads = int(v.get("n_beads", base.n_beads))
    if "stiffness_scale" in v or "n_beads" in v:
        law = SimConfig.stiffness_ref_force_n * math.sqrt(beads / REFERENCE_BEADS)
        changes["stiffness_ref_force_n"] = law * float(v.get("stiffness_scale", 1.0))
    if "tint_count" in v or "tint_strength" in v:
        order = np.arange(len(BEAD_PALETTE_RGB)) if palette_order is None else palette_order
        count = int(v.get("tint_count", len(base.bead_tints_rgb)))
        strength = float(v.get("tint_strength", 1.0))
        tints = [BEAD_PALETTE_RGB[int(i)] for i in order[:count]]
        changes["bead_tints_rgb"] = tuple(
            tuple(float(np.clip(1.0 - strength * (1.0 - c), 0.05, 1.0)) for c in t) for t in tints
        )
    if "bubble_max_diameter_mm" in v:
        changes["bubble_diameter_range_mm"] = (
            BUBBLE_MIN_DIAMETER_MM,
            float(v["bubble_max_diameter_mm"]),
        )
    if "led_colour_temperature_k" in v:
        changes["led_colour_rgb"] = colour_temperature_rgb(float(v["led_colour_temperature_k"]))
    wb = list(base.white_balance_rgb)
    wb[0] = float(v.get("white_balance_red", wb[0]))
    wb[2] = float(v.get("white_balance_blue", wb[2]))
    changes["white_balance_rgb"] = tuple(wb)
    for field, prefix in (
        ("camera_offset_mm", "camera_offset"),
        ("crop_offset_mm", "crop_offset"),
    ):
        old = getattr(base, field)
        changes[field] = (
            float(v.get(f"{prefix}_x_mm", old[0])),
            float(v.get(f"{prefix}_y_mm", old[1])),
        )
    old_tilt = base.camera_tilt_deg
    changes["camera_tilt_deg"] = (
        float(v.get("camera_tilt_rows_deg", old_tilt[0])),
        float(v.get("camera_tilt_cols_deg", old_tilt[1])),
    )
    return dataclasses.replace(base, **changes)


def factor_table() -> str:
    """A Markdown table of every factor: group, name, unit, training and held-out ranges."""

    def fmt(ranges: tuple[tuple[float, float], ...], integer: bool) -> str:
        def num(x: float) -> str:
            return str(int(x)) if integer or float(x).is_integer() else f"{x:g}"

        return " and ".join(f"{num(lo)} to {num(hi)}" for lo, hi in ranges)

    rows = [
        "| group | factor | unit | training range | held-out range | meaning |",
        "|---|---|---|---|---|---|",
    ]
    for f in FACTORS:
        heldout = f"**{fmt(f.heldout, f.integer)}**" if f.heldout else "as training"
        rows.append(
            f"| {f.group} | `{f.name}` | {f.unit} | {fmt((f.train,), f.integer)} | "
            f"{heldout} | {f.doc} |"
        )
    return "\n".join(rows)
