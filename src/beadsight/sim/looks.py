"""Looks: families of simulated sensors that look as unlike each other as two renderers.

A user's pouch will not look like our simulator: other beads (clear, coloured, one
colour, a mix; larger or smaller), another background (the black sheet, a light
one, a print), other light (one LED or a ring of them, glare) and another camera
(blur, noise, a different fisheye or crop). A *look family* is a region of the
renderer's look fields (:class:`~beadsight.sim.config.SimConfig`'s "look" group
plus bead size, light and camera fields): each family gives every field it sets a
range, and a pouch of that family draws one value from each range.

Splits (:data:`LOOK_SPLITS`):

* ``"train"``: the families a base model may be trained on;
* ``"heldout"``: two families **never** trained or tuned on, the team's
  foreign-look benchmark. ``clear_print`` (clear, dark-rimmed beads on a light,
  printed background) and ``grey_ring`` (a monochrome camera, small beads, a ring
  of LEDs with strong glare, a blurred, noisy, mis-sized fisheye): each differs from
  every training family in its background, its camera or both, as a sensor built
  by someone else would.

A draw picks a family uniformly from the split (or takes the one family named)
and then every parameter, always with the same number of random numbers, so the
same generator state gives the same look whatever the family. A look is applied
*on top of* a base config (a :mod:`~beadsight.sim.variety` build, say): fields the
family sets replace the base's, all others (mechanics, rig, image size) stay.
With no look at all, the renderer draws exactly today's reference look.
``docs/simulator.md`` lists the families, their ranges and how they compare with
photos of the real sensor.
"""

from __future__ import annotations

import colorsys
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from beadsight.errors import ConfigError
from beadsight.sim.config import LOOK_SPLITS, SimConfig

PARAM_DRAWS = 32  # uniforms drawn for a family's parameters (the same for every family)
TINT_DRAWS = 12  # uniforms drawn for its bead tints
Tints = tuple[tuple[float, float, float], ...]


@dataclass(frozen=True)
class Uniform:
    """A float uniform in [low, high]."""

    low: float
    high: float

    def value(self, u: float) -> float:
        return float(self.low + u * (self.high - self.low))


@dataclass(frozen=True)
class Integer:
    """An integer uniform in [low, high], both included."""

    low: int
    high: int

    def value(self, u: float) -> int:
        return int(min(self.low + math.floor(u * (self.high - self.low + 1)), self.high))


@dataclass(frozen=True)
class Choice:
    """One of ``options``, each equally likely."""

    options: tuple[Any, ...]

    def value(self, u: float) -> Any:
        return self.options[min(int(u * len(self.options)), len(self.options) - 1)]


Spec = Uniform | Integer | Choice


# --- bead tints (linear RGB multipliers, max channel <= 1) ------------------------------
def _clear_pink(u: np.ndarray) -> Tints:
    """Clear beads with a pink to magenta tint (as in photos of the real sensor): 3 shades."""
    pink = 0.06 + 0.22 * u[0]  # how pink the bag is
    blue = 0.2 + 0.4 * u[4]  # how much of the pink's loss blue shares (low: magenta)
    return tuple(
        (1.0, round(1.0 - pink * (0.8 + 0.4 * u[1 + k]), 4), round(1.0 - blue * pink, 4))
        for k in range(3)
    )


def _colourless(u: np.ndarray) -> Tints:
    """Clear beads, barely tinted (cool to warm): 2 shades."""
    warm = 0.08 * (u[0] - 0.5)
    return ((1.0, round(1.0 - abs(warm), 4), round(1.0 - max(warm, 0.0) * 2, 4)), (0.96, 0.98, 1.0))


def _one_colour(u: np.ndarray) -> Tints:
    """Every bead one colour: a random hue, moderately to strongly saturated, 2 shades."""
    hue, sat = float(u[0]), 0.35 + 0.5 * float(u[1])
    r, g, b = colorsys.hsv_to_rgb(hue, sat, 1.0)
    dark = 0.85 + 0.1 * float(u[2])
    return ((r, g, b), (r * dark, g * dark, b * dark))


def _vivid_mix(u: np.ndarray) -> Tints:
    """A mix of clear and strongly coloured beads: 2 clear, 3 to 5 vivid hues."""
    count = 3 + int(u[0] * 3)
    tints: list[tuple[float, float, float]] = [(0.97, 0.97, 1.0), (1.0, 0.98, 0.96)]
    for k in range(count):
        hue = (float(u[1]) + k / count + 0.1 * float(u[2 + k])) % 1.0
        tints.append(colorsys.hsv_to_rgb(hue, 0.7 + 0.25 * float(u[7]), 1.0))
    return tuple(tints)


def _milky(u: np.ndarray) -> Tints:
    """Frosted, milky-white beads with a faint cool or warm cast: 2 shades."""
    cast = 0.1 * (float(u[0]) - 0.5)
    return ((1.0 - max(cast, 0), 1.0, 1.0 + min(cast, 0)), (0.94, 0.95, 0.97))


def _reference_tints(u: np.ndarray) -> Tints | None:
    """The base's own tints (the reference bag, or a variety build's)."""
    return None


@dataclass(frozen=True)
class LookFamily:
    """One family of looks: its name, what it is, and the range of every field it sets.

    params: (SimConfig field, spec) pairs, drawn in this order; fields of tuple type
    are set from a float spec as that value repeated (greys) unless named below.
    tints: bead tints from uniforms (None keeps the base's). doc: one line.
    """

    name: str
    doc: str
    params: tuple[tuple[str, Spec], ...]
    tints: Callable[[np.ndarray], Tints | None] = _reference_tints

    def __post_init__(self) -> None:
        names = {f.name for f in dataclasses.fields(SimConfig)}
        unknown = [n for n, _ in self.params if n not in names and n not in _DERIVED]
        if unknown or len(self.params) > PARAM_DRAWS:
            raise ConfigError(f"look family {self.name!r}: unknown fields {unknown}")

    def draw(self, u: np.ndarray, tint_u: np.ndarray) -> dict[str, Any]:
        """Parameter values at quantiles ``u`` (PARAM_DRAWS,) and ``tint_u`` (TINT_DRAWS,)."""
        values: dict[str, Any] = {
            name: spec.value(float(q)) for (name, spec), q in zip(self.params, u, strict=False)
        }
        tints = self.tints(tint_u)
        if tints is not None:
            values["bead_tints_rgb"] = tuple(
                tuple(float(np.clip(c, 0.05, 1.0)) for c in t) for t in tints
            )
        return values


# Values that set a field through a rule rather than directly.
_DERIVED = ("background_warmth",)


def _apply_derived(values: dict[str, Any]) -> dict[str, Any]:
    out = dict(values)
    if "background_warmth" in out:
        w = float(out.pop("background_warmth"))  # -1 cool .. +1 warm
        out["background_tint_rgb"] = (1.0 + 0.08 * w, 1.0, 1.0 - 0.12 * w)
    return out


_CAMERA_TRAIN = (  # a camera like the reference's, give or take (train families)
    ("noise_std", Uniform(0.8, 4.0)),
    ("defocus_sigma_mm", Uniform(0.0, 0.15)),
    ("lens_focal_error", Uniform(-0.03, 0.03)),
    ("lens_distortion_k", Uniform(-0.04, 0.04)),
    ("crop_scale_error", Uniform(-0.02, 0.02)),
)

FAMILIES: dict[str, LookFamily] = {
    f.name: f
    for f in (
        LookFamily(
            "coloured",
            "today's look: pale mixed tints on the black cover, four corner LEDs",
            (
                ("bead_body_level", Uniform(185.0, 225.0)),
                ("rim_darken", Uniform(0.5, 0.72)),
                ("rim_width", Uniform(0.11, 0.17)),
                ("specular_peak", Uniform(220.0, 340.0)),
                ("background_level", Uniform(10.0, 28.0)),
                ("glare_level", Uniform(5.0, 14.0)),
                ("bead_diameter_mm", Uniform(3.7, 4.3)),
                *_CAMERA_TRAIN,
            ),
        ),
        LookFamily(
            "clear",
            "clear, faintly pink beads with dark refraction rims on a dark sheet",
            (
                ("bead_body_level", Uniform(150.0, 210.0)),
                ("bead_opacity", Uniform(0.85, 0.97)),
                ("bead_clarity", Uniform(0.55, 0.85)),
                ("bead_shading", Uniform(0.1, 0.35)),
                ("rim_darken", Uniform(0.8, 0.97)),
                ("rim_width", Uniform(0.16, 0.26)),
                ("caustic_gain", Uniform(0.3, 0.8)),
                ("specular_peak", Uniform(200.0, 320.0)),
                ("background_level", Uniform(30.0, 100.0)),
                ("background_warmth", Uniform(0.0, 1.0)),
                ("mottle_amplitude", Uniform(3.0, 10.0)),
                ("glare_level", Uniform(6.0, 20.0)),
                ("bead_diameter_mm", Uniform(3.6, 4.6)),
                ("noise_std", Uniform(0.8, 4.0)),
                ("defocus_sigma_mm", Uniform(0.0, 0.3)),  # photos of the real sensor are soft
                ("lens_focal_error", Uniform(-0.03, 0.03)),
                ("lens_distortion_k", Uniform(-0.04, 0.04)),
                ("crop_scale_error", Uniform(-0.02, 0.02)),
            ),
            _clear_pink,
        ),
        LookFamily(
            "mono",
            "one bead colour, opaque with soft rims, on a grey sheet, lit from one or two sides",
            (
                ("bead_body_level", Uniform(170.0, 230.0)),
                ("bead_opacity", Uniform(0.95, 1.0)),
                ("bead_shading", Uniform(0.5, 0.8)),
                ("rim_darken", Uniform(0.1, 0.35)),
                ("caustic_gain", Uniform(0.0, 0.2)),
                ("specular_peak", Uniform(120.0, 260.0)),
                ("background_level", Uniform(45.0, 100.0)),
                ("background_warmth", Uniform(-1.0, 1.0)),
                ("background_pattern", Choice(("mottle", "stripes"))),
                ("pattern_contrast", Uniform(0.0, 0.25)),
                ("pattern_period_mm", Uniform(3.0, 8.0)),
                ("n_leds", Integer(1, 2)),
                ("led_rotation_deg", Uniform(-45.0, 45.0)),
                ("glare_level", Uniform(3.0, 12.0)),
                ("bead_diameter_mm", Uniform(4.2, 4.8)),
                *_CAMERA_TRAIN,
            ),
            _one_colour,
        ),
        LookFamily(
            "vivid",
            "a mix of clear and strongly coloured beads on a light sheet, a ring of LEDs",
            (
                ("bead_body_level", Uniform(190.0, 240.0)),
                ("bead_opacity", Uniform(0.85, 0.97)),
                ("rim_darken", Uniform(0.4, 0.7)),
                ("specular_peak", Uniform(250.0, 400.0)),
                ("background_level", Uniform(120.0, 190.0)),
                ("background_warmth", Uniform(-1.0, 1.0)),
                ("mottle_amplitude", Uniform(4.0, 15.0)),
                ("seam_level", Uniform(40.0, 120.0)),
                ("n_leds", Integer(5, 8)),
                ("glare_level", Uniform(15.0, 40.0)),
                ("glare_sigma_mm", Uniform(2.5, 5.0)),
                ("camera_saturation", Uniform(1.0, 1.4)),
                ("bead_diameter_mm", Uniform(3.5, 4.2)),
                *_CAMERA_TRAIN,
            ),
            _vivid_mix,
        ),
        LookFamily(
            "milky",
            "frosted milky beads with faint rims on a dark blue-grey sheet, three LEDs",
            (
                ("bead_body_level", Uniform(120.0, 180.0)),
                ("bead_opacity", Uniform(0.7, 0.85)),
                ("bead_shading", Uniform(0.25, 0.5)),
                ("rim_darken", Uniform(0.2, 0.45)),
                ("rim_width", Uniform(0.2, 0.35)),
                ("caustic_gain", Uniform(0.0, 0.25)),
                ("specular_peak", Uniform(80.0, 180.0)),
                ("background_level", Uniform(15.0, 40.0)),
                ("background_warmth", Uniform(-1.0, -0.3)),
                ("n_leds", Integer(3, 3)),
                ("led_rotation_deg", Uniform(-45.0, 45.0)),
                ("glare_level", Uniform(2.0, 10.0)),
                ("bead_diameter_mm", Uniform(3.5, 4.4)),
                ("motion_blur_fraction", Uniform(0.0, 0.3)),
                *_CAMERA_TRAIN,
            ),
            _milky,
        ),
        # --- held out: never train or tune on these ------------------------------------
        LookFamily(
            "clear_print",
            "HELD OUT: clear dark-rimmed beads on a light, printed background (dots, grid)",
            (
                ("bead_body_level", Uniform(170.0, 230.0)),
                ("bead_opacity", Uniform(0.85, 0.95)),
                ("bead_clarity", Uniform(0.6, 0.9)),
                ("bead_shading", Uniform(0.1, 0.3)),
                ("rim_darken", Uniform(0.8, 0.95)),
                ("rim_width", Uniform(0.15, 0.25)),
                ("caustic_gain", Uniform(0.2, 0.6)),
                ("background_level", Uniform(150.0, 210.0)),
                ("background_warmth", Uniform(-0.5, 0.5)),
                ("background_pattern", Choice(("dots", "grid"))),
                ("pattern_contrast", Uniform(0.3, 0.6)),
                ("pattern_period_mm", Uniform(1.5, 4.0)),
                ("mottle_amplitude", Uniform(2.0, 8.0)),
                ("seam_level", Uniform(100.0, 160.0)),
                ("glare_level", Uniform(5.0, 15.0)),
                ("bead_diameter_mm", Uniform(3.6, 4.4)),
                *_CAMERA_TRAIN,
            ),
            _colourless,
        ),
        LookFamily(
            "grey_ring",
            "HELD OUT: monochrome camera, small beads, a ring of LEDs with strong glare, "
            "a blurred, noisy, mis-sized fisheye",
            (
                ("camera_saturation", Uniform(0.0, 0.15)),
                ("bead_diameter_mm", Uniform(2.9, 3.3)),
                ("bead_body_level", Uniform(160.0, 220.0)),
                ("rim_darken", Uniform(0.4, 0.7)),
                ("specular_peak", Uniform(300.0, 500.0)),
                ("background_level", Uniform(60.0, 110.0)),
                ("background_pattern", Choice(("speckle",))),
                ("pattern_contrast", Uniform(0.2, 0.45)),
                ("n_leds", Integer(6, 10)),
                ("glare_level", Uniform(30.0, 60.0)),
                ("glare_sigma_mm", Uniform(4.0, 7.0)),
                ("noise_std", Uniform(4.5, 7.0)),
                ("defocus_sigma_mm", Uniform(0.15, 0.3)),
                ("lens_focal_error", Choice((-0.08, 0.08))),
                ("lens_distortion_k", Uniform(-0.12, 0.12)),
                ("crop_scale_error", Uniform(0.04, 0.08)),
            ),
            _milky,
        ),
    )
}
FAMILY_NAMES = tuple(FAMILIES)


def resolve_looks(looks: str) -> tuple[str, ...]:
    """The families ``looks`` names: a split of :data:`LOOK_SPLITS` or one family."""
    if looks in LOOK_SPLITS:
        return LOOK_SPLITS[looks]
    if looks in FAMILIES:
        return (looks,)
    raise ConfigError(
        f"looks must be a split {tuple(LOOK_SPLITS)} or a family {FAMILY_NAMES}, got {looks!r}"
    )


@dataclass(frozen=True)
class LookSample:
    """One drawn look: its family, the values drawn, and ``base`` with them applied."""

    family: str
    values: dict[str, Any]
    config: SimConfig

    def to_dict(self) -> dict[str, Any]:
        return {"family": self.family, "values": dict(self.values)}


def apply_look(family: str, values: dict[str, Any], base: SimConfig) -> SimConfig:
    """``base`` with a family's drawn ``values`` applied (fields it does not set stay)."""
    if family not in FAMILIES:
        resolve_looks(family)  # raises, naming the valid ones
    return dataclasses.replace(base, **_apply_derived(values))


def sample_look(rng: np.random.Generator, looks: str, base: SimConfig | None = None) -> LookSample:
    """Draw one look from ``looks`` (a split or a family) and apply it to ``base``.

    Always uses ``1 + PARAM_DRAWS + TINT_DRAWS`` uniforms of ``rng``, whatever the family.
    """
    families = resolve_looks(looks)
    base = base if base is not None else SimConfig()
    pick = rng.random()
    u = rng.random(PARAM_DRAWS)
    tint_u = rng.random(TINT_DRAWS)
    family = families[min(int(pick * len(families)), len(families) - 1)]
    values = FAMILIES[family].draw(u, tint_u)
    return LookSample(family, values, apply_look(family, values, base))


class LookDraws:
    """The looks of a session's pouches, drawn in order from their own stream.

    looks: a split or family (see :func:`resolve_looks`); seed: the stream's seed.
    ``get(i, base)`` is pouch ``i``'s look applied to ``base`` (the same for every caller).
    """

    def __init__(self, looks: str, seed: np.random.SeedSequence | int):
        self.looks = looks
        self.families = resolve_looks(looks)
        self._rng = np.random.default_rng(seed)
        self._draws: list[tuple[str, dict[str, Any]]] = []

    def drawn(self, index: int) -> tuple[str, dict[str, Any]]:
        """(family, values) of pouch ``index``."""
        while len(self._draws) <= index:
            sample = sample_look(self._rng, self.looks)
            self._draws.append((sample.family, sample.values))
        return self._draws[index]

    def get(self, index: int, base: SimConfig) -> LookSample:
        family, values = self.drawn(index)
        return LookSample(family, values, apply_look(family, values, base))


def family_table() -> str:
    """A Markdown table of the families: split, name, what it is, and its ranges."""

    def fmt(spec: Spec) -> str:
        if isinstance(spec, Choice):
            return "/".join(str(o) for o in spec.options)
        return f"{spec.low:g}..{spec.high:g}"

    split_of = {f: s for s, fams in LOOK_SPLITS.items() for f in fams}
    rows = ["| split | family | look | ranges |", "|---|---|---|---|"]
    for f in FAMILIES.values():
        ranges = ", ".join(f"`{n}` {fmt(s)}" for n, s in f.params)
        tints = f.tints.__name__.strip("_").replace("_", " ")
        rows.append(f"| {split_of[f.name]} | `{f.name}` | {f.doc} (tints: {tints}) | {ranges} |")
    return "\n".join(rows)
