"""The camera's view of the pouch in sensor space: beads, bubbles, LEDs, lens, noise.

The camera looks at the beads from behind, through an acrylic window; the finger
side of the pouch is covered by a black sheet, so the finger itself is never seen.
A frame is composed as:

1. a static background (black cover through water, faint mottling of the vinyl,
   the pouch's welded seam at the border), rendered once;
2. bubbles, then beads, alpha-composited back to front from pre-rendered
   *sprites*: a translucent sphere with a dark refraction rim, a soft caustic,
   and four specular highlights (one per corner LED) whose arrangement depends on
   where the bead sits; a compressed bead is larger and shows a flat contact
   patch with dimmed highlights. Sprites are cached by quantised radius,
   flatness, image zone and sub-pixel phase, so a frame is ~100 small blits.
   Radius and flatness are quantised with a fixed random threshold per bead
   (ordered dithering): each bead steps to its next sprite at its own depth, so
   the beads under a finger together still show the depth continuously rather
   than in a few coarse steps;
3. the LEDs' illumination and the lens's vignetting (one static gain map), a
   per-frame brightness flicker, static glare of the LEDs on the acrylic
   (:mod:`beadsight.sim.optics.light`); a camera mounted, focused or set up unlike the
   reference build adds its view, exposure and blur (:mod:`beadsight.sim.optics.camera`);
4. rounding to uint8, sensor noise (pre-generated noise tiles at random offsets,
   added with saturating uint8 arithmetic) and optional MJPG-like JPEG compression.

All randomness comes from the generator passed in (noise offsets, flicker), so a
renderer never disturbs the mechanics' random stream.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import cv2
import numpy as np

from beadsight.sim.config import SimConfig
from beadsight.sim.optics.camera import Exposure
from beadsight.sim.optics.light import led_positions_mm, pixel_mm
from beadsight.sim.pouch import PouchView

# --- sprite quantisation ------------------------------------------------------------
RADIUS_STEP = 0.025  # sprites exist for radii on a geometric grid with this relative step
FLAT_LEVELS = 7  # flatness levels 0..1
ZONES = 5  # highlight arrangement quantised on a ZONES x ZONES grid over the image
PHASES = 4  # sub-pixel positions per pixel, per axis (frames up to FINE_PHASE_MAX_PX)
FINE_PHASE_MAX_PX = 320  # larger images (the one behind raw frames) use whole-pixel positions
SPRITE_CACHE_BYTES = 96 * 2**20  # sprites kept, all looks together (see SpriteCache)
_LOG_STEP = math.log1p(RADIUS_STEP)

# --- appearance (radiance units: 0..255 under full illumination) --------------------
# A look's levels (bead body, opacity, clarity, shading, rim, caustic, specular peak,
# background, seam) are SimConfig fields (sim/looks.py draws them); these shape it.
CAUSTIC_SIGMA = 0.32  # of the radius
SPECULAR_SIGMA = 0.075  # of the radius (at least SPECULAR_MIN_PX)
SPECULAR_MIN_PX = 0.55
SPECULAR_SPREAD = 0.21  # the four highlights sit this far (of the radius) from their centre
HIGHLIGHT_SHIFT = 0.32  # the highlight cluster moves toward the image centre (of the radius)
CONTACT_TONE = 0.74  # a flattened face against the window is flatter and a little darker
CONTACT_RADIUS = 0.82  # radius of the full contact patch (of the apparent radius)
CONTACT_RING = 40.0  # bright contact line at the patch's edge
CONTACT_SPECULAR_LOSS = 0.85  # highlights fade on a flattened bead
BUBBLE_CENTRE = 150.0  # a bubble's bright centre (it acts as a lens)
BUBBLE_RING = 22.0  # its thick dark ring (total internal reflection)
BUBBLE_RING_WIDTH = 0.38  # of the radius
BUBBLE_CENTRE_ALPHA = 0.35
BUBBLE_RING_ALPHA = 0.92
MOTTLE_SCALE_MM = 3.0
CLARITY_CORE = 0.8  # a clear bead's transparent core: opacity recovers over the outer 20 %
SPECKLE_SCALE_MM = 0.5  # grain of the "speckle" background print
NOISE_TILES = 2  # pre-generated noise fields, sampled at random offsets


Sprite = tuple[np.ndarray, np.ndarray]  # (1 - alpha, premultiplied colour), (h, h, 3) f32


class SpriteCache:
    """Sprites by look and frame size, shared by every renderer of that look in the process.

    A sprite is a pure function of the look (a :class:`SimConfig`), the frame size and its
    key, while a session makes a new renderer for every pouch (and a test or a replay for
    every session): a 2-press session at 64 px spent a third of its time making sprites.
    Past :data:`SPRITE_CACHE_BYTES` the looks used longest ago are dropped first, then the
    oldest quarter of the sprites of the look being drawn.
    """

    def __init__(self, max_bytes: int = SPRITE_CACHE_BYTES):
        self.max_bytes = max_bytes
        self._looks: OrderedDict[tuple[SimConfig, int], dict[int, Sprite]] = OrderedDict()
        self._look_bytes: dict[tuple[SimConfig, int], int] = {}
        self._bytes = 0
        self._lock = threading.Lock()

    def sprites(self, look: tuple[SimConfig, int]) -> dict[int, Sprite]:
        """The look's sprites by key (read-only for the caller; add with :meth:`add`)."""
        with self._lock:
            sprites = self._looks.get(look)
            if sprites is None:
                sprites = self._looks[look] = {}
                self._look_bytes[look] = 0
            self._looks.move_to_end(look)
            return sprites

    def add(self, look: tuple[SimConfig, int], key: int, sprite: Sprite) -> None:
        size = sprite[0].nbytes + sprite[1].nbytes
        with self._lock:
            if look not in self._looks:  # dropped since the caller's sprites() call
                self._looks[look], self._look_bytes[look] = {}, 0
            sprites = self._looks[look]
            if key in sprites:
                return
            sprites[key] = sprite
            self._look_bytes[look] += size
            self._bytes += size
            while self._bytes > self.max_bytes:
                older = next((k for k in self._looks if k != look), None)
                if older is not None:
                    del self._looks[older]
                    self._bytes -= self._look_bytes.pop(older)
                    continue
                for old in list(sprites)[: max(len(sprites) // 4, 1)]:  # oldest first
                    a, b = sprites.pop(old)
                    self._look_bytes[look] -= a.nbytes + b.nbytes
                    self._bytes -= a.nbytes + b.nbytes


SPRITES = SpriteCache()


class SensorRenderer:
    """Render :class:`PouchView` states as ``(S, S, 3)`` uint8 RGB sensor-space frames.

    size_px: the frame side S. appearance_seed: seeds the static look of the pouch
    (the same for every renderer of one pouch, whatever its size). rng: per-frame
    randomness (noise offsets, flicker). noise: add sensor noise (off for the
    high-resolution image behind raw frames, which gets its noise in raw space).
    jpeg_quality: JPEG-compress each frame (None: off).
    """

    def __init__(
        self,
        config: SimConfig,
        size_px: int,
        appearance_seed: np.random.SeedSequence | int,
        rng: np.random.Generator,
        *,
        noise: bool = True,
        jpeg_quality: int | None = None,
    ):
        self.config = config
        self.size = int(size_px)
        self.rng = rng
        self.noise = noise
        self.jpeg_quality = jpeg_quality
        self.px_per_mm = self.size / config.sensor_size_mm
        look = np.random.default_rng(appearance_seed)
        self._background = self._make_background(look)
        # each object's quantisation threshold, part of the pouch's static look
        self._dither = look.random(config.n_beads + config.n_bubbles)
        self._exposure = Exposure(config, self.size, config.seam_level * self._cover_tint())
        self._scratch = np.empty((self.size, self.size, 3), np.float32)
        self._noise_pad = max(8, self.size // 4)
        self._noise = noise_tiles(
            rng, config.noise_std if noise else 0.0, (self.size + self._noise_pad,) * 2
        )
        self._saturation = saturation_matrix(config.camera_saturation)
        tints = np.asarray(config.bead_tints_rgb, np.float32)
        self._tints = tints
        self._look = (config, self.size)  # its sprites' key in SPRITES
        self._max_rq = int(math.ceil(math.log(self.size) / _LOG_STEP)) + 1
        self.phases = PHASES if self.size <= FINE_PHASE_MAX_PX else 1
        # Half-size of the sprite for each quantised radius.
        radii = np.exp(np.arange(self._max_rq + 1) * _LOG_STEP)
        self._half = np.ceil(radii + 1.5).astype(np.int64)

    # --- static layers ----------------------------------------------------------------
    def _pixel_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """x_mm (1, S) of column centres, y_mm (S, 1) of row centres (printer frame)."""
        return pixel_mm(self.config, self.size)

    def _cover_tint(self) -> np.ndarray:
        return np.asarray(self.config.background_tint_rgb, np.float32)

    def _make_background(self, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        s = self.size
        x, y = self._pixel_mm()
        # Low-frequency mottling: blurred noise drawn on a fixed coarse grid, so it looks
        # the same at every image size.
        coarse = max(4, int(cfg.sensor_size_mm / MOTTLE_SCALE_MM))
        field = rng.standard_normal((coarse, coarse)).astype(np.float32)
        field = cv2.resize(field, (s, s), interpolation=cv2.INTER_CUBIC)
        level = cfg.background_level + cfg.mottle_amplitude * field
        if cfg.background_pattern != "mottle" and cfg.pattern_contrast > 0:
            ink = background_print(cfg, x, y, rng, s)
            level = level * (1.0 - cfg.pattern_contrast * ink)
        outside = np.maximum(np.abs(x), np.abs(y)) > cfg.pouch_half_mm
        level = np.where(outside, cfg.seam_level + 2 * cfg.mottle_amplitude * field, level)
        bg = np.repeat(level[..., None], 3, axis=2).astype(np.float32)
        bg *= self._cover_tint()
        return np.ascontiguousarray(np.clip(bg, 0, 255))

    # --- sprites ------------------------------------------------------------------------
    def _keys(self, view: PouchView) -> tuple[list, ...]:
        """Sprite keys and clipped blit rectangles (image and sprite) for every visible object."""
        s = self.size
        ppm = self.px_per_mm
        smm = self.config.sensor_size_mm
        phases = self.phases
        row = (0.5 - view.xy_mm[:, 1] / smm) * s  # continuous pixel coordinates
        col = (0.5 - view.xy_mm[:, 0] / smm) * s
        r_px = np.maximum(view.radius_mm * ppm, 0.5)
        dither = self._dither[view.index]  # floor(x + u), u uniform: unbiased in x
        rq = np.floor(np.log(r_px) / _LOG_STEP + dither)
        rq = np.clip(rq, 0, self._max_rq).astype(np.int64)
        fq = np.floor(view.flatness * (FLAT_LEVELS - 1) + (dither + 0.5) % 1.0)
        fq = np.clip(fq, 0, FLAT_LEVELS - 1)
        zr = np.clip((row / s * ZONES).astype(np.int64), 0, ZONES - 1)
        zc = np.clip((col / s * ZONES).astype(np.int64), 0, ZONES - 1)
        ar, ac = np.floor(row), np.floor(col)
        pr = np.clip(((row - ar) * phases).astype(np.int64), 0, phases - 1)
        pc = np.clip(((col - ac) * phases).astype(np.int64), 0, phases - 1)
        key = view.tint.astype(np.int64) + 1  # 0 = bubble
        for value, size in (
            (rq, self._max_rq + 1),
            (fq.astype(np.int64), FLAT_LEVELS),
            (zr, ZONES),
            (zc, ZONES),
            (pr, PHASES),
            (pc, PHASES),
        ):
            key = key * size + value
        h = self._half[rq]
        r0, c0 = ar.astype(np.int64) - h, ac.astype(np.int64) - h
        r1, c1 = r0 + 2 * h + 1, c0 + 2 * h + 1
        visible = (r1 > 0) & (c1 > 0) & (r0 < s) & (c0 < s)
        sr0, sc0 = np.maximum(-r0, 0), np.maximum(-c0, 0)
        sr1 = 2 * h + 1 - np.maximum(r1 - s, 0)
        sc1 = 2 * h + 1 - np.maximum(c1 - s, 0)
        cols = (
            key,
            np.maximum(r0, 0),
            np.minimum(r1, s),
            np.maximum(c0, 0),
            np.minimum(c1, s),
            sr0,
            sr1,
            sc0,
            sc1,
        )
        return tuple(c[visible].tolist() for c in cols)

    def _add_sprite(self, key: int) -> Sprite:
        sprite = self._make_sprite(key)
        SPRITES.add(self._look, key, sprite)
        return sprite

    def _make_sprite(self, key: int) -> Sprite:
        """(1 - alpha) (h, h, 3) f32 and premultiplied colour (h, h, 3) f32, radiance units."""
        key, pc = divmod(key, PHASES)
        key, pr = divmod(key, PHASES)
        key, zc = divmod(key, ZONES)
        key, zr = divmod(key, ZONES)
        key, fq = divmod(key, FLAT_LEVELS)
        tint, rq = divmod(key, self._max_rq + 1)
        r = math.exp(rq * _LOG_STEP)
        half = int(self._half[rq])
        k = np.arange(2 * half + 1, dtype=np.float32) - half + 0.5
        dy = (k - (pr + 0.5) / self.phases)[:, None]
        dx = (k - (pc + 0.5) / self.phases)[None, :]
        flat = fq / (FLAT_LEVELS - 1)
        # Position of the bead in the image, -0.5..0.5, for the highlight arrangement.
        q = np.array([(zr + 0.5) / ZONES - 0.5, (zc + 0.5) / ZONES - 0.5])
        if tint == 0:
            alpha, premult = _bubble(dx, dy, r, flat, q, self._led_q(), self.config)
        else:
            alpha, premult = _bead(
                dx, dy, r, flat, q, self._led_q(), self._tints[tint - 1], self.config
            )
        # Three-channel (not broadcast) so the blit is two plain cv2 calls.
        inv_alpha = np.repeat((1.0 - alpha)[..., None], 3, axis=2).astype(np.float32)
        return inv_alpha, np.ascontiguousarray(premult.astype(np.float32))

    def _led_q(self) -> np.ndarray:
        """(4, 2) LED positions in normalised image coordinates (row, col), -0.5..0.5."""
        smm = self.config.sensor_size_mm
        return np.array([(-ly / smm, -lx / smm) for lx, ly in led_positions_mm(self.config)])

    # --- frames -------------------------------------------------------------------------
    def composite(self, view: PouchView) -> np.ndarray:
        """Radiance image (S, S, 3) float32 before illumination (a reused buffer)."""
        out = self._scratch
        np.copyto(out, self._background)
        cache, make = SPRITES.sprites(self._look), self._add_sprite
        multiply, add = cv2.multiply, cv2.add
        for key, r0, r1, c0, c1, sr0, sr1, sc0, sc1 in zip(*self._keys(view), strict=True):
            sprite = cache.get(key)
            inv_alpha, premult = sprite if sprite is not None else make(key)
            patch = out[r0:r1, c0:c1]
            multiply(patch, inv_alpha[sr0:sr1, sc0:sc1], dst=patch)  # in place: "over"
            add(patch, premult[sr0:sr1, sc0:sc1], dst=patch)
        return out

    def render(self, view: PouchView) -> np.ndarray:
        """(S, S, 3) uint8 RGB frame."""
        out = self.composite(view)
        gain = 1.0
        if self.config.flicker > 0:
            gain += self.config.flicker * float(self.rng.standard_normal())
        frame = self._exposure(out, gain)
        if self._saturation is not None:
            frame = cv2.transform(frame, self._saturation)
        if self._noise:
            plus, minus = self._noise[int(self.rng.integers(len(self._noise)))]
            oy, ox = (int(v) for v in self.rng.integers(0, self._noise_pad, 2))
            s = self.size
            cv2.add(frame, plus[oy : oy + s, ox : ox + s], dst=frame)
            cv2.subtract(frame, minus[oy : oy + s, ox : ox + s], dst=frame)
        if self.jpeg_quality is not None:
            frame = jpeg_roundtrip(frame, self.jpeg_quality, rgb=True)
        return frame


def noise_tiles(
    rng: np.random.Generator, std: float, hw: tuple[int, int]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Gaussian noise fields (rounded) as (positive part, negative part) uint8 pairs.

    Adding the first and subtracting the second with saturating uint8 arithmetic
    adds the noise to a frame; frames sample the tiles at random offsets.
    """
    if std <= 0:
        return []
    tiles = []
    for _ in range(NOISE_TILES):
        n = np.rint(rng.normal(0.0, std, (*hw, 3)))
        tiles.append((np.clip(n, 0, 255).astype(np.uint8), np.clip(-n, 0, 255).astype(np.uint8)))
    return tiles


def jpeg_roundtrip(frame: np.ndarray, quality: int, rgb: bool) -> np.ndarray:
    """Compress and decompress a uint8 colour frame as JPEG (the camera's MJPG stream)."""
    bgr = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR) if rgb else frame
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 colour images
        raise RuntimeError("JPEG encoding failed")
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return cv2.cvtColor(out, cv2.COLOR_BGR2RGB) if rgb else out


def _gauss(dx: np.ndarray, dy: np.ndarray, cx: float, cy: float, sigma: float) -> np.ndarray:
    """Separable 2-D Gaussian (peak 1) on the sprite grid: an outer product of two 1-D ones."""
    k = -0.5 / (sigma * sigma)
    return np.exp(k * (dy - cy) ** 2) * np.exp(k * (dx - cx) ** 2)


def _highlights(
    dx: np.ndarray, dy: np.ndarray, r: float, q: np.ndarray, leds: np.ndarray, sigma: float
) -> np.ndarray:
    """Sum of the four LEDs' specular spots (peak 1 each), arranged by image position q."""
    centre = -HIGHLIGHT_SHIFT * (q / 0.5) * r  # toward the image centre
    spots = 0.0
    for led in leds:
        v = led - q
        v = v / max(float(np.hypot(*v)), 1e-6)
        cy, cx = centre + SPECULAR_SPREAD * r * v
        spots = spots + _gauss(dx, dy, cx, cy, sigma)
    return spots


def _bead(dx, dy, r, flat, q, leds, tint, look: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """A translucent bead: alpha (h, w) and premultiplied colour (h, w, 3), radiance units.

    look: the config whose look fields (body level, opacity, clarity, shading, rim,
    caustic, specular peak) shape the bead.
    """
    base = look.bead_body_level
    shading = look.bead_shading
    dist = np.sqrt(dx * dx + dy * dy)
    d = dist / r
    edge = np.clip(r - dist + 0.5, 0.0, 1.0)  # anti-aliased outline
    inside = np.clip(1.0 - d * d, 0.0, 1.0)
    body = base * (1.0 - shading + shading * np.sqrt(inside))
    body *= 1.0 - look.rim_darken * np.exp(-(((1.0 - d) / look.rim_width) ** 2))
    centre = HIGHLIGHT_SHIFT * (q / 0.5) * r * 0.8  # caustic opposite the highlights
    body += look.caustic_gain * base * _gauss(dx, dy, centre[1], centre[0], CAUSTIC_SIGMA * r)
    if flat > 0:
        rc = CONTACT_RADIUS * r * math.sqrt(flat)
        patch = np.clip(rc - dist + 0.5, 0.0, 1.0)
        flat_tone = base * CONTACT_TONE
        body = body * (1 - patch * flat) + flat_tone * patch * flat
        ring = np.exp(-(((dist - rc) / max(0.08 * r, 0.5)) ** 2))
        body += CONTACT_RING * flat * ring
    sigma = max(SPECULAR_SIGMA * r * (1 + 1.5 * flat), SPECULAR_MIN_PX)
    spec = (
        look.specular_peak
        * (1 - CONTACT_SPECULAR_LOSS * flat)
        * _highlights(dx, dy, r, q, leds, sigma)
    )
    alpha = edge * look.bead_opacity
    if look.bead_clarity > 0:
        # A clear bead: the background shows through its core, its rim stays opaque
        # (the dark refraction ring); a flattened face against the window stays clear.
        core = np.clip((CLARITY_CORE - d) / CLARITY_CORE, 0.0, 1.0)
        alpha = alpha * (1.0 - look.bead_clarity * np.sqrt(core))
    # Premultiplied: the body is seen through alpha, the specular reflection is added light.
    premult = (body * alpha)[..., None] * np.asarray(tint)[None, None, :] + (spec * edge)[..., None]
    return alpha, premult


def _bubble(dx, dy, r, flat, q, leds, look: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """An air bubble: thick dark ring, bright centre, strong highlights (alpha, premult)."""
    dist = np.sqrt(dx * dx + dy * dy)
    d = dist / r
    edge = np.clip(r - dist + 0.5, 0.0, 1.0)
    width = BUBBLE_RING_WIDTH * (1 - 0.5 * flat)
    ring = np.clip((d - (1 - width)) / max(width * 0.5, 1e-3), 0.0, 1.0)
    ring = ring * ring * (3 - 2 * ring)
    level = BUBBLE_CENTRE * (1 - ring) + BUBBLE_RING * ring
    alpha = edge * (BUBBLE_CENTRE_ALPHA * (1 - ring) + BUBBLE_RING_ALPHA * ring)
    sigma = max(SPECULAR_SIGMA * 1.3 * r, SPECULAR_MIN_PX)
    spec = 1.2 * look.specular_peak * _highlights(dx, dy, 0.8 * r, q, leds, sigma)
    premult = np.repeat((level * alpha + spec * edge)[..., None], 3, axis=2)
    return alpha, premult


def saturation_matrix(saturation: float) -> np.ndarray | None:
    """(3, 3) float32 colour matrix scaling RGB saturation about the luma (None at 1).

    0 makes a monochrome camera (every channel the luma), above 1 boosts colour.
    """
    if saturation == 1.0:
        return None
    luma = np.array([0.299, 0.587, 0.114], np.float32)  # ITU-R BT.601, RGB order
    grey = np.repeat(luma[None, :], 3, axis=0)
    return (saturation * np.eye(3, dtype=np.float32) + (1.0 - saturation) * grey).astype(np.float32)


def background_print(
    config: SimConfig, x: np.ndarray, y: np.ndarray, rng: np.random.Generator, size: int
) -> np.ndarray:
    """(S, S) float 0..1: the print on the background (1: ink), anti-aliased.

    x: (1, S) mm, y: (S, 1) mm of pixel centres; the print is turned by a random angle
    and shifted by a random phase (from ``rng``, the pouch's static look). Patterns:
    dots (a square lattice of dots), grid (thin lines), stripes, speckle (fine grain).
    """
    period = config.pattern_period_mm
    angle = rng.uniform(0.0, math.pi / 2)
    phase = rng.uniform(0.0, period, 2)
    c, s_ = math.cos(angle), math.sin(angle)
    u = (x * c - y * s_ + phase[0]) / period  # in periods
    v = (x * s_ + y * c + phase[1]) / period
    px = period * size / config.sensor_size_mm  # pixels per period (anti-aliasing width)
    aa = 1.0 / max(px, 1e-6)  # one pixel, in periods

    def line(t: np.ndarray, half_width: float) -> np.ndarray:
        dist = np.abs(t - np.round(t))  # 0..0.5 periods from the nearest line
        return np.clip((half_width - dist) / aa + 0.5, 0.0, 1.0)

    pattern = config.background_pattern
    if pattern == "dots":
        du, dv = u - np.round(u), v - np.round(v)
        dist = np.sqrt(du * du + dv * dv)
        ink = np.clip((0.3 - dist) / aa + 0.5, 0.0, 1.0)
    elif pattern == "grid":
        ink = np.maximum(line(u, 0.08), line(v, 0.08))
    elif pattern == "stripes":
        ink = line(u, 0.25)
    else:  # speckle: fine random grain on a grid of SPECKLE_SCALE_MM
        cells = max(4, int(config.sensor_size_mm / SPECKLE_SCALE_MM))
        grain = rng.random((cells, cells)).astype(np.float32)
        ink = cv2.resize(grain, (size, size), interpolation=cv2.INTER_LINEAR)
    return np.asarray(ink, np.float32)
