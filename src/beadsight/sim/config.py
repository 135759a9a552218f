"""Simulator configuration: one frozen dataclass, with presets for 75, 100 and 125 beads.

Every number the simulator uses lives here with its unit in the field name and a
one-line comment. The defaults model the published sensor and its calibration
rig (reference-facts sections 1 and 5); ``docs/simulator.md`` explains each group
of fields and how the force law was chosen.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from beadsight.config import REFERENCE_CENTRE_XY_MM, ConfigError, SensorGeometry, _Serializable

# Pale, translucent tints (linear RGB multipliers) of the hydrogel beads. Water beads
# are sold in mixed colours; a bag of them is a handful of tints.
MIXED_TINTS_RGB = (
    (0.93, 0.95, 1.00),  # clear
    (0.62, 0.80, 1.00),  # blue
    (0.66, 0.98, 0.72),  # green
    (1.00, 0.72, 0.80),  # pink
    (1.00, 0.86, 0.55),  # amber
    (0.82, 0.72, 1.00),  # violet
)

PRESET_BEAD_COUNTS = (75, 100, 125)  # pouch variants of the published sensor
# How a session's drawn presses move (beadsight.sim.press.draw_profile): the reference
# pattern, or a mix with long holds, slow ramps and depth changes while held.
PRESS_PROFILES = ("reference", "mixed")
# Look families of the simulator (beadsight.sim.looks) by split; "heldout" families are the
# foreign-look benchmark, never trained on. Here, without numpy, for the CLI's --help.
LOOK_SPLITS: dict[str, tuple[str, ...]] = {
    "train": ("coloured", "clear", "mono", "vivid", "milky"),
    "heldout": ("clear_print", "grey_ring"),
}
WARM_WHITE_RGB = (1.0, 0.97, 0.92)  # colour of the reference build's LEDs (linear RGB)
COVER_TINT_RGB = (0.92, 0.97, 1.0)  # water over the black vinyl cover: slightly cool
BACKGROUND_PATTERNS = ("mottle", "dots", "grid", "stripes", "speckle")  # background prints


@dataclass(frozen=True)
class SimConfig(_Serializable):
    """All parameters of the simulated sensor, rig and camera.

    Positions are millimetres from the sensor centre in the printer frame unless a
    field says "printer" (absolute printer coordinates). Build presets with
    :meth:`preset`; change fields with :func:`dataclasses.replace`.
    """

    # --- pouch ------------------------------------------------------------------------
    n_beads: int = 100  # hydrogel beads in the pouch (bag variants: 75, 100, 125)
    sensor_size_mm: float = 41.0  # side of the square field of view (sensor-space image)
    pouch_size_mm: float = 40.0  # inner side of the pouch; beads stay inside +-half of it
    bead_diameter_mm: float = 4.0  # mean diameter of a saturated bead
    bead_diameter_spread_mm: float = 0.35  # standard deviation of bead diameters
    n_bubbles: int = 5  # small air bubbles left in on purpose
    bubble_diameter_range_mm: tuple[float, float] = (0.7, 2.2)  # uniform in this range
    bead_tints_rgb: tuple[tuple[float, float, float], ...] = MIXED_TINTS_RGB  # bead colours
    min_spacing_fraction: float = 0.86  # beads overlap in projection down to this x (r_i + r_j)

    # --- mechanics ----------------------------------------------------------------------
    stiffness_ref_force_n: float = 4.3  # equilibrium force at stiffness_ref_depth_mm, centre
    stiffness_ref_depth_mm: float = 1.0  # depth of the reference point of the force law
    stiffness_exponent: float = 2.25  # F = F_ref (d / d_ref)^p: the pouch stiffens nonlinearly
    edge_stiffening: float = 0.2  # fractional extra stiffness when the finger reaches the edge
    packing_stiffness_gain: float = 0.35  # stiffness change per fractional change of local packing
    press_stiffness_spread: float = 0.04  # per-press random stiffness factor (std), not visible
    relaxation_fraction: float = 0.22  # viscoelastic overshoot: extra force per unit of load rate
    relaxation_time_s: float = 0.6  # time constant of the force's stress relaxation
    push_gain_mm_per_mm: float = 0.7  # outward displacement at the finger rim per mm of depth
    push_decay_mm: float = 3.5  # the outward push decays with this length beyond the rim
    membrane_falloff_mm: float = 1.2  # the pouch membrane bends over this width at the rim
    push_gain_spread: float = 0.25  # per-bead, per-press log-normal spread of the push gain
    bead_lag_s: float = 0.09  # viscous lag (time constant) of beads moving with the finger
    bead_return_lag_s: float = 0.35  # slower drift back when the load comes off (hysteresis)
    bead_lag_spread: float = 0.3  # per-bead log-normal spread of the lag time constants
    jitter_mm: float = 0.025  # RMS of each bead's random jitter about its place
    jitter_time_s: float = 0.25  # correlation time of the jitter
    drift_mm_per_sqrt_s: float = 0.004  # slow random walk of the resting arrangement
    settle_noise_mm_per_mm: float = 0.35  # random re-settling after a press, per mm of peak depth
    hysteresis_fraction: float = 0.18  # fraction of the peak displacement left after release
    edge_margin_mm: float = 3.5  # beads closer than this to the pouch wall move less
    bubble_mobility: float = 2.2  # bubbles move this much more than beads
    max_compression: float = 0.5  # largest vertical strain of a bead under the finger
    pouch_slack_mm: float = 0.5  # depth taken up by the water layer before beads compress

    # --- rig: printer (reference-facts section 5) ------------------------------------
    surface_z_mm: float = 129.0  # printer Z at which the finger touches the pouch
    centre_xy_mm: tuple[float, float] = REFERENCE_CENTRE_XY_MM  # printer XY of the sensor centre
    clear_z_mm: float = 137.5  # printer Z between presses
    press_z_range_mm: tuple[float, float] = (127.0, 128.0)  # press depth Z, uniform
    finger_radius_mm: float = 6.25  # flat cylindrical finger, 12.5 mm diameter
    press_range_mm: float = 13.75  # presses uniform within +-this of the centre (X and Y)
    travel_feed_mm_min: float = 700.0  # G1 F700: moves between presses
    descend_feed_mm_min: float = 200.0  # G1 F200: descent onto the pouch
    rise_feed_mm_min: float = 700.0  # G1 F700: rise after the dwell
    dwell_s: float = 1.0  # G4 P1000 at the bottom of a press
    pause_s: float = 0.5  # time at clear Z between presses (G-code round trips, logging)

    # --- rig: scale (HX711 on an Arduino) ---------------------------------------------
    scale_rate_hz: float = 10.0  # HX711 output data rate (10 or 80 samples/s)
    scale_noise_g: float = 0.3  # RMS noise of one reading, grams
    scale_drift_g_per_sqrt_s: float = 0.04  # random-walk tare drift, grams per sqrt(second)
    scale_resolution_g: float = 0.01  # readings are printed with 2 decimals

    # --- camera -------------------------------------------------------------------------
    image_size_px: int = 256  # side of the sensor-space frames
    fps: float = 30.0  # camera frame rate
    frame_time_jitter_s: float = 0.001  # RMS jitter of frame timestamps
    start_time_s: float = 1.7e9  # unix time of the simulated clock's start
    noise_std: float = 2.0  # sensor noise in sensor-space frames, 0..255 units (RMS)
    raw_noise_std: float = 4.0  # sensor noise in raw 1280x1024 frames, 0..255 units (RMS)
    flicker: float = 0.006  # RMS frame-to-frame brightness fluctuation (fraction)
    vignetting: float = 0.45  # brightness lost at the image corners (fraction)
    led_offset_mm: float = 15.0  # the four LEDs sit at (+-this, +-this) mm, behind the acrylic
    led_height_mm: float = 11.0  # distance of the LEDs from the bead layer
    background_level: float = 18.0  # black cover seen through water, 0..255
    jpeg_quality: int | None = None  # MJPG-like compression of sensor-space frames (None: off)
    raw_jpeg_quality: int | None = 85  # MJPG compression of raw frames (None: off)
    raw_render_px: int = 768  # sensor-space resolution rendered for raw frames

    # --- light: how one build's LEDs differ from another's ------------------------------
    led_intensity: float = 1.0  # brightness of the LEDs relative to the reference build
    led_colour_rgb: tuple[float, float, float] = WARM_WHITE_RGB  # LED colour (linear RGB)
    led_rotation_deg: float = 0.0  # the square of four LEDs is turned by this about the centre
    ambient_light: float = 0.22  # light scattered inside the housing, relative to the LEDs' peak

    # --- camera: mounting, lens and settings that differ from the reference build --------
    exposure_gain: float = 1.0  # exposure x sensor gain relative to the reference build
    white_balance_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)  # per-channel gains
    camera_offset_mm: tuple[float, float] = (0.0, 0.0)  # camera shifted by (x, y), printer frame
    camera_tilt_deg: tuple[float, float] = (0.0, 0.0)  # tilt about the image's row, column axes
    camera_roll_deg: float = 0.0  # rotation about the optical axis
    lens_focal_error: float = 0.0  # the fisheye's focal length differs by this fraction
    lens_distortion_k: float = 0.0  # fisheye r = f theta (1 + k theta^2) instead of f theta
    crop_scale_error: float = 0.0  # the preprocessing crop is this fraction larger (zoom out)
    crop_offset_mm: tuple[float, float] = (0.0, 0.0)  # the crop sits off the optical axis (x, y)

    # --- image ------------------------------------------------------------------------
    motion_blur_fraction: float = 0.0  # exposure reaches this far into the previous frame period
    defocus_sigma_mm: float = 0.0  # Gaussian blur of an out-of-focus lens, mm on the pouch

    # --- look: how the beads, the background and the light appear (sim/looks.py) --------
    # Defaults are the reference look (coloured beads on the black cover); radiance
    # units are 0..255 under full illumination.
    bead_body_level: float = 205.0  # body brightness of a bead at its centre
    bead_opacity: float = 0.9  # beads are translucent: the background shows through a little
    bead_clarity: float = 0.0  # clear beads: opacity falls by this fraction toward the centre
    bead_shading: float = 0.45  # body brightness falls by this fraction from centre to rim
    rim_darken: float = 0.62  # refraction makes a dark ring at the bead's outline
    rim_width: float = 0.14  # width of that ring, fraction of the radius
    caustic_gain: float = 0.35  # light focused by the bead, opposite its highlights
    specular_peak: float = 300.0  # peak of each LED's specular highlight (saturates)
    background_tint_rgb: tuple[float, float, float] = COVER_TINT_RGB  # of background_level
    background_pattern: str = "mottle"  # mottle, dots, grid, stripes or speckle (a print)
    pattern_contrast: float = 0.0  # the print darkens the background by this fraction
    pattern_period_mm: float = 2.5  # spacing of the print's dots, lines or stripes
    mottle_amplitude: float = 5.0  # low-frequency texture of the background, radiance units
    seam_level: float = 85.0  # the pouch's welded seam at the border of the field of view
    n_leds: int = 4  # LEDs around the camera (4: the reference's square; else a ring)
    glare_level: float = 9.0  # reflections of the LEDs on the acrylic, radiance units
    glare_sigma_mm: float = 3.0  # size of one LED's glare spot
    camera_saturation: float = 1.0  # colour saturation of the camera (0: monochrome sensor)

    def __post_init__(self) -> None:
        tints = tuple(tuple(float(c) for c in t) for t in self.bead_tints_rgb)
        object.__setattr__(self, "bead_tints_rgb", tints)
        for name in (
            "bubble_diameter_range_mm",
            "centre_xy_mm",
            "press_z_range_mm",
            "led_colour_rgb",
            "white_balance_rgb",
            "camera_offset_mm",
            "camera_tilt_deg",
            "crop_offset_mm",
            "background_tint_rgb",
        ):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        for name in ("n_beads", "n_bubbles", "image_size_px", "raw_render_px", "n_leds"):
            value = getattr(self, name)
            if int(value) != value:
                raise ConfigError(f"SimConfig.{name} must be an integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        self._check_ranges()

    def _check_ranges(self) -> None:
        def need(ok: bool, name: str, expected: str) -> None:
            if not ok:
                raise ConfigError(
                    f"SimConfig.{name} must be {expected}, got {getattr(self, name)!r}"
                )

        need(1 <= self.n_beads <= 400, "n_beads", "in [1, 400]")
        need(0 <= self.n_bubbles <= 50, "n_bubbles", "in [0, 50]")
        need(self.sensor_size_mm > 0, "sensor_size_mm", "> 0")
        need(0 < self.pouch_size_mm, "pouch_size_mm", "> 0")
        need(
            0 < self.bead_diameter_mm < self.pouch_size_mm / 2,
            "bead_diameter_mm",
            "in (0, pouch_size_mm / 2)",
        )
        need(
            0 <= self.bead_diameter_spread_mm < self.bead_diameter_mm / 3,
            "bead_diameter_spread_mm",
            "in [0, bead_diameter_mm / 3)",
        )
        lo, hi = self.bubble_diameter_range_mm
        need(
            len(self.bubble_diameter_range_mm) == 2 and 0 < lo <= hi,
            "bubble_diameter_range_mm",
            "(low, high) with 0 < low <= high",
        )
        need(
            len(self.bead_tints_rgb) >= 1 and all(len(t) == 3 for t in self.bead_tints_rgb),
            "bead_tints_rgb",
            "a non-empty tuple of (r, g, b) tints",
        )
        need(0.5 <= self.min_spacing_fraction <= 1.0, "min_spacing_fraction", "in [0.5, 1]")
        for name in (
            "stiffness_ref_force_n",
            "stiffness_ref_depth_mm",
            "stiffness_exponent",
            "relaxation_time_s",
            "push_decay_mm",
            "membrane_falloff_mm",
            "bead_lag_s",
            "bead_return_lag_s",
            "jitter_time_s",
            "edge_margin_mm",
            "bubble_mobility",
            "finger_radius_mm",
            "travel_feed_mm_min",
            "descend_feed_mm_min",
            "rise_feed_mm_min",
            "scale_rate_hz",
            "scale_resolution_g",
            "fps",
            "led_height_mm",
        ):
            need(getattr(self, name) > 0, name, "> 0")
        for name in (
            "edge_stiffening",
            "packing_stiffness_gain",
            "press_stiffness_spread",
            "relaxation_fraction",
            "push_gain_mm_per_mm",
            "push_gain_spread",
            "bead_lag_spread",
            "jitter_mm",
            "drift_mm_per_sqrt_s",
            "settle_noise_mm_per_mm",
            "pouch_slack_mm",
            "dwell_s",
            "pause_s",
            "scale_noise_g",
            "scale_drift_g_per_sqrt_s",
            "frame_time_jitter_s",
            "noise_std",
            "raw_noise_std",
            "flicker",
            "led_offset_mm",
        ):
            need(getattr(self, name) >= 0, name, ">= 0")
        need(0 <= self.hysteresis_fraction < 1, "hysteresis_fraction", "in [0, 1)")
        need(0 < self.max_compression < 0.9, "max_compression", "in (0, 0.9)")
        need(0 <= self.vignetting < 1, "vignetting", "in [0, 1)")
        need(0 <= self.background_level <= 255, "background_level", "in [0, 255]")
        need(len(self.centre_xy_mm) == 2, "centre_xy_mm", "(x, y)")
        self._check_variety_ranges(need)
        z_lo, z_hi = self.press_z_range_mm
        need(
            len(self.press_z_range_mm) == 2 and z_lo <= z_hi < self.clear_z_mm,
            "press_z_range_mm",
            "(low, high) with low <= high < clear_z_mm",
        )
        need(self.surface_z_mm < self.clear_z_mm, "surface_z_mm", "below clear_z_mm")
        need(
            self.press_range_mm + self.finger_radius_mm <= self.sensor_size_mm / 2,
            "press_range_mm",
            "such that the finger stays inside the field of view",
        )
        need(8 <= self.image_size_px <= 2048, "image_size_px", "in [8, 2048]")
        need(64 <= self.raw_render_px <= 2048, "raw_render_px", "in [64, 2048]")
        # The frame period must fit the jitter comfortably, so timestamps stay increasing.
        need(
            self.frame_time_jitter_s * 8 < 1 / self.fps,
            "frame_time_jitter_s",
            "well below the frame period (8 sigma < 1/fps)",
        )
        for name in ("jpeg_quality", "raw_jpeg_quality"):
            q = getattr(self, name)
            need(q is None or (int(q) == q and 1 <= q <= 100), name, "None or an integer 1..100")

    def _check_variety_ranges(self, need) -> None:
        """Ranges of the fields that let builds differ (light, camera, image)."""
        need(0 < self.led_intensity <= 10, "led_intensity", "in (0, 10]")
        need(0 < self.exposure_gain <= 10, "exposure_gain", "in (0, 10]")
        need(0 <= self.ambient_light <= 5, "ambient_light", "in [0, 5]")
        for name in ("led_colour_rgb", "white_balance_rgb"):
            v = getattr(self, name)
            need(len(v) == 3 and all(0 < c <= 4 for c in v), name, "(r, g, b), each in (0, 4]")
        for name in ("camera_offset_mm", "crop_offset_mm"):
            v = getattr(self, name)
            need(len(v) == 2 and all(abs(c) <= 5 for c in v), name, "(x, y) within +-5 mm")
        tilt = self.camera_tilt_deg
        need(len(tilt) == 2 and all(abs(c) <= 15 for c in tilt), "camera_tilt_deg", "within +-15")
        need(abs(self.camera_roll_deg) <= 45, "camera_roll_deg", "within +-45")
        need(abs(self.led_rotation_deg) <= 45, "led_rotation_deg", "within +-45")
        need(abs(self.lens_focal_error) <= 0.3, "lens_focal_error", "within +-0.3")
        need(abs(self.lens_distortion_k) <= 0.3, "lens_distortion_k", "within +-0.3")
        need(abs(self.crop_scale_error) <= 0.3, "crop_scale_error", "within +-0.3")
        need(0 <= self.motion_blur_fraction < 1, "motion_blur_fraction", "in [0, 1)")
        need(0 <= self.defocus_sigma_mm <= 2, "defocus_sigma_mm", "in [0, 2]")
        self._check_look_ranges(need)

    def _check_look_ranges(self, need) -> None:
        """Ranges of the look fields (beads, background, LEDs, glare; sim/looks.py)."""
        need(0 < self.bead_body_level <= 255, "bead_body_level", "in (0, 255]")
        for name in ("bead_opacity", "bead_clarity", "bead_shading", "rim_darken"):
            need(0 <= getattr(self, name) <= 1, name, "in [0, 1]")
        need(0 < self.rim_width <= 0.5, "rim_width", "in (0, 0.5]")
        need(0 <= self.caustic_gain <= 2, "caustic_gain", "in [0, 2]")
        need(0 <= self.specular_peak <= 1000, "specular_peak", "in [0, 1000]")
        v = self.background_tint_rgb
        need(
            len(v) == 3 and all(0 <= c <= 2 for c in v),
            "background_tint_rgb",
            "(r, g, b) in [0, 2]",
        )
        need(
            self.background_pattern in BACKGROUND_PATTERNS,
            "background_pattern",
            f"one of {BACKGROUND_PATTERNS}",
        )
        need(0 <= self.pattern_contrast <= 1, "pattern_contrast", "in [0, 1]")
        need(0.3 <= self.pattern_period_mm <= 20, "pattern_period_mm", "in [0.3, 20]")
        need(0 <= self.mottle_amplitude <= 60, "mottle_amplitude", "in [0, 60]")
        need(0 <= self.seam_level <= 255, "seam_level", "in [0, 255]")
        need(1 <= self.n_leds <= 12, "n_leds", "in [1, 12]")
        need(0 <= self.glare_level <= 255, "glare_level", "in [0, 255]")
        need(0 < self.glare_sigma_mm <= 20, "glare_sigma_mm", "in (0, 20]")
        need(0 <= self.camera_saturation <= 3, "camera_saturation", "in [0, 3]")

    # --- derived ---------------------------------------------------------------------
    @property
    def geometry(self) -> SensorGeometry:
        """The sensor geometry of the frames this configuration renders."""
        return SensorGeometry(
            sensor_size_mm=self.sensor_size_mm,
            image_size_px=self.image_size_px,
            finger_radius_mm=self.finger_radius_mm,
            press_range_mm=self.press_range_mm,
        )

    @property
    def pouch_half_mm(self) -> float:
        return self.pouch_size_mm / 2

    def equilibrium_force_n(self, depth_mm: float) -> float:
        """Force of the force law at ``depth_mm`` at the centre, average packing (N)."""
        if depth_mm <= 0:
            return 0.0
        return self.stiffness_ref_force_n * (depth_mm / self.stiffness_ref_depth_mm) ** (
            self.stiffness_exponent
        )

    def depth_range_mm(self) -> tuple[float, float]:
        """Finger depth below the pouch surface at the deepest and shallowest press Z."""
        lo, hi = self.press_z_range_mm
        return self.surface_z_mm - hi, self.surface_z_mm - lo

    def replace(self, **changes: Any) -> SimConfig:
        return dataclasses.replace(self, **changes)

    @classmethod
    def preset(cls, n_beads: int = 100, **changes: Any) -> SimConfig:
        """The pouch variants of the published sensor: 75, 100 or 125 beads.

        More beads fill more of the pouch: the pouch is stiffer (more of the load is
        carried by beads rather than water) and shows fewer gaps and bubbles.
        """
        if n_beads not in PRESET_BEAD_COUNTS:
            raise ConfigError(
                f"SimConfig.preset: n_beads must be one of {PRESET_BEAD_COUNTS}, got {n_beads!r}"
            )
        fill = n_beads / 100
        base = cls(
            n_beads=n_beads,
            stiffness_ref_force_n=round(cls.stiffness_ref_force_n * math.sqrt(fill), 3),
            n_bubbles={75: 6, 100: 5, 125: 4}[n_beads],
        )
        return dataclasses.replace(base, **changes) if changes else base
