"""The light inside the sensor: four LEDs, the housing's ambient light, glare, LED colour.

All maps are static (computed once per renderer) and sampled at the centres of a
``size x size`` sensor-space image; positions are millimetres from the sensor
centre in the printer frame (printer +X is image -column, +Y image -row).
"""

from __future__ import annotations

import math

import numpy as np

from beadsight.sim.config import SimConfig

# Colour temperature -> linear RGB of a white LED: the blackbody's colour over the
# visible band, sampled at three wavelengths standing for the camera's R, G, B
# filters, normalised so the brightest channel is 1.
_RGB_WAVELENGTHS_M = (600e-9, 540e-9, 460e-9)
_PLANCK_C2_M_K = 1.4388e-2  # second radiation constant h c / k


def colour_temperature_rgb(kelvin: float) -> tuple[float, float, float]:
    """Linear RGB (max channel 1) of a light source of colour temperature ``kelvin`` (K).

    Planck's law at the wavelengths of ``_RGB_WAVELENGTHS_M``: 2700 K is orange-warm,
    ~5000 K is near neutral, 6500 K and above are blue-ish.
    """
    if not 1000.0 <= kelvin <= 20000.0:
        raise ValueError(f"colour temperature must be in [1000, 20000] K, got {kelvin!r}")
    radiance = [lam**-5 / math.expm1(_PLANCK_C2_M_K / (lam * kelvin)) for lam in _RGB_WAVELENGTHS_M]
    # Relative to a 5000 K source, so that a near-daylight LED looks white.
    neutral = [lam**-5 / math.expm1(_PLANCK_C2_M_K / (lam * 5000.0)) for lam in _RGB_WAVELENGTHS_M]
    rel = [r / n for r, n in zip(radiance, neutral, strict=True)]
    top = max(rel)
    return (rel[0] / top, rel[1] / top, rel[2] / top)


def pixel_mm(config: SimConfig, size: int, pad: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """x_mm (1, S) of column centres, y_mm (S, 1) of row centres (printer frame).

    pad: extend the grid by this many pixels on every side (S + 2 pad values each).
    """
    centres = (np.arange(-pad, size + pad) + 0.5) / size
    coord = (0.5 - centres) * config.sensor_size_mm
    return coord[None, :], coord[:, None]


def led_positions_mm(config: SimConfig) -> list[tuple[float, float]]:
    """(x, y) of the LEDs, mm: four at the corners of a square of half-side
    ``led_offset_mm`` (the reference), any other ``n_leds`` evenly on the circle through
    those corners, the first at the (+, +) corner (one LED lights from one side); all
    turned by ``led_rotation_deg``."""
    a = config.led_offset_mm
    if config.n_leds == 4:
        corners = [(sx * a, sy * a) for sx in (-1, 1) for sy in (-1, 1)]
    else:
        n, rho = config.n_leds, a * math.sqrt(2.0)
        angles = [math.pi / 4 + 2 * math.pi * k / n for k in range(n)]
        corners = [(rho * math.cos(t), rho * math.sin(t)) for t in angles]
    if config.led_rotation_deg == 0:
        return corners
    t = math.radians(config.led_rotation_deg)
    c, s = math.cos(t), math.sin(t)
    return [(x * c - y * s, x * s + y * c) for x, y in corners]


def led_light(config: SimConfig, size: int, pad: int = 0) -> np.ndarray:
    """(S, S) float64 LED light on the bead layer plus ambient light, peak LED light 1
    inside the image ((S + 2 pad, S + 2 pad) with ``pad``)."""
    x, y = pixel_mm(config, size, pad)
    h = config.led_height_mm
    light = np.zeros((size + 2 * pad, size + 2 * pad), np.float64)
    for lx, ly in led_positions_mm(config):
        rho2 = (x - lx) ** 2 + (y - ly) ** 2
        light += h**3 / (rho2 + h * h) ** 1.5  # Lambertian point source, 1 directly below
    inner = light[pad : pad + size, pad : pad + size]
    return light / inner.max() + config.ambient_light


def lens_falloff(config: SimConfig, size: int) -> np.ndarray:
    """(S, S) float64 relative illumination of the lens: 1 - vignetting at the corners."""
    x, y = pixel_mm(config, size)
    r2 = (x * x + y * y) / (config.sensor_size_mm**2 / 2)  # 1 at the image corners
    return 1.0 - config.vignetting * r2


def camera_gain_rgb(config: SimConfig) -> np.ndarray:
    """(3,) float64 exposure x white balance x LED colour x intensity."""
    wb = np.asarray(config.white_balance_rgb, np.float64)
    colour = np.asarray(config.led_colour_rgb, np.float64)
    return config.led_intensity * config.exposure_gain * wb * colour


def illumination(config: SimConfig, size: int) -> np.ndarray:
    """(S, S, 3) float32 gain from radiance to pixel values: LEDs, lens falloff, camera.

    The LED light with the lens's falloff is normalised to peak 1 for the reference
    build, then scaled by :func:`camera_gain_rgb`.
    """
    light = led_light(config, size) * lens_falloff(config, size)
    light /= light.max()
    illum = light[..., None] * camera_gain_rgb(config)[None, None, :]
    return np.ascontiguousarray(illum.astype(np.float32))


def split_illumination(config: SimConfig, size: int, pad: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`illumination` split into the part fixed to the pouch and the part fixed
    to the camera, for a camera that does not see the pouch as the reference does.

    returns: world (S + 2 pad, S + 2 pad, 3) float32 LED light on the pouch, also
    ``pad`` pixels beyond the image; camera (S, S, 3) float32 lens falloff x camera
    gain. Inside the image their product is :func:`illumination` (up to rounding).
    """
    world = led_light(config, size, pad)
    lens = lens_falloff(config, size)
    world /= (world[pad : pad + size, pad : pad + size] * lens).max()
    camera = lens[..., None] * camera_gain_rgb(config)[None, None, :]
    return (
        np.ascontiguousarray(np.repeat(world[..., None], 3, axis=2).astype(np.float32)),
        np.ascontiguousarray(camera.astype(np.float32)),
    )


def glare(config: SimConfig, size: int) -> np.ndarray:
    """(S, S, 3) uint8 reflections of the LEDs on the acrylic window."""
    x, y = pixel_mm(config, size)
    spots = np.zeros((size, size), np.float64)
    for lx, ly in led_positions_mm(config):
        spots += np.exp(-((x - lx) ** 2 + (y - ly) ** 2) / (2 * config.glare_sigma_mm**2))
    out = config.glare_level * spots[..., None] * camera_gain_rgb(config)[None, None, :]
    return np.ascontiguousarray(np.clip(np.rint(out), 0, 255).astype(np.uint8))
