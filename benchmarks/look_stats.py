"""Look families beside photos of the real sensor: colour, bead size and rim contrast.

Every image goes through the same pipeline: a raw fisheye frame (the simulator's
``render_raw``, 1280 x 1024; the photos as they are, e.g. 1920 x 1080) through the
reference preprocessing (:meth:`beadsight.preprocess.Preprocessor.reference`,
bilinear) to a 256 px sensor-space image. On it:

* ``mean_rgb`` / ``std_rgb``: per-channel mean and standard deviation, 0..255;
* ``bead_px``: the bead spacing, px at 256: the first peak of the radial profile of
  the grey image's autocorrelation (normalised by the mask's own, so masked bars do
  not count), between ``SPACING_PX``; in a packed layer, about a bead's diameter
  (4 mm beads: ~25 px). None when there is no peak in that range;
* ``blob_px``: the dominant blob diameter: the scale ``sigma`` that maximises the
  mean squared scale-normalised Laplacian of Gaussian, as ``2 sqrt(2) sigma``
  (highlights and gaps count as blobs too, so it is below the bead size);
* ``rim_contrast``: thin dark outlines (refraction rims, dark gaps between beads):
  the mean black top-hat of the grey image (closing minus image, an ellipse of
  about half the bead size) over its median; 0: no dark lines thinner than a bead.

The photos of the reference repository's ``Unwarp_Fisheye/Fisheye_Imgs`` show the
pouch behind a light grid (a calibration jig); its bars are masked out (rows and
columns of the unwarped image that are mostly bright and colourless), and photos
without beads (only the grid on a plain background) are skipped by name
(``--photos-glob``, default ``test*.jpg``).

    .venv/bin/python benchmarks/look_stats.py --photos DIR [--pouches 3] \\
        [--image docs/images/looks.png] [--speed]

``--speed`` adds rendering speed at 64 px per CPU-second (each family's mean over
its pouches, against the reference look). Prints a table and a JSON object last.
Held-out families are measured here, never tuned to anything.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from beadsight.preprocess import Preprocessor
from beadsight.sim import PouchSimulator, SimConfig, SimulatedSession
from beadsight.sim.looks import FAMILY_NAMES, LOOK_SPLITS, sample_look

SIZE = 256  # sensor-space side the statistics are measured at
SIGMAS = np.geomspace(2.0, 16.0, 22)  # LoG scales searched, px at 256
SPACING_PX = (8, 48)  # bead spacings searched, px at 256 (1.3 to 7.7 mm)
BAR_MIN_FRACTION = 0.45  # a row/column mostly bright and colourless is a bar of the jig
BAR_VALUE, BAR_CHROMA = 150, 45  # HSV value above / saturation below: a bar pixel
BAR_DILATE_PX = 4
PRESS_XY_MM, PRESS_DEPTH_MM, PRESS_S = (3.0, -2.0), 1.4, 1.0  # the "pressed" column
TILE_PX = 128  # side of one picture in the grid
DT = 1 / 30


def grid_mask(rgb: np.ndarray) -> np.ndarray:
    """(S, S) bool, True where a pixel is not on a bar of the calibration grid."""
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    bar = (hsv[..., 2] > BAR_VALUE) & (hsv[..., 1] < BAR_CHROMA)
    rows = bar.mean(1) > BAR_MIN_FRACTION
    cols = bar.mean(0) > BAR_MIN_FRACTION
    masked = (rows[:, None] | cols[None, :]).astype(np.uint8)
    kernel = np.ones((2 * BAR_DILATE_PX + 1,) * 2, np.uint8)
    return ~cv2.dilate(masked, kernel).astype(bool)


def image_stats(rgb: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Statistics of one (S, S, 3) uint8 RGB sensor-space image (see the module doc)."""
    mask = np.ones(rgb.shape[:2], bool) if mask is None else mask
    px = rgb[mask].astype(np.float64)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    energy = []
    for sigma in SIGMAS:
        log = sigma * sigma * cv2.Laplacian(cv2.GaussianBlur(grey, (0, 0), sigma), cv2.CV_32F)
        margin = int(math.ceil(2 * sigma))
        inner = cv2.erode(mask.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8))
        inner[:margin], inner[-margin:], inner[:, :margin], inner[:, -margin:] = 0, 0, 0, 0
        sel = inner.astype(bool) if inner.any() else mask
        energy.append(float((log[sel] ** 2).mean()))
    sigma = float(SIGMAS[int(np.argmax(energy))])
    bead_px = 2 * math.sqrt(2) * sigma
    side = 2 * int(round(bead_px / 4)) + 1  # about half a bead, odd
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    hat = cv2.morphologyEx(grey, cv2.MORPH_BLACKHAT, kernel)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((side, side), np.uint8)).astype(bool)
    inner = inner if inner.any() else mask
    rim = float(hat[inner].mean() / max(float(np.median(grey[inner])), 1e-6))
    return {
        "mean_rgb": px.mean(0).round(1).tolist(),
        "std_rgb": px.std(0).round(1).tolist(),
        "bead_px": None if math.isnan(spacing := bead_spacing_px(grey, mask)) else spacing,
        "blob_px": round(bead_px, 1),
        "rim_contrast": round(rim, 3),
    }


def bead_spacing_px(grey: np.ndarray, mask: np.ndarray) -> float:
    """First peak of the masked autocorrelation's radial profile in SPACING_PX (or NaN)."""
    m = mask.astype(np.float64)
    g = (grey - grey[mask].mean()) * m
    n = 2 * max(grey.shape)  # zero padding: no wrap-around
    f, fm = np.fft.rfft2(g, (n, n)), np.fft.rfft2(m, (n, n))
    ac = np.fft.irfft2(f * np.conj(f), (n, n))
    count = np.fft.irfft2(fm * np.conj(fm), (n, n))
    ac = np.fft.fftshift(ac / np.maximum(count, 1.0))
    yy, xx = np.mgrid[-n // 2 : n // 2, -n // 2 : n // 2]
    r = np.rint(np.hypot(yy, xx)).astype(np.int64).ravel()
    lo, hi = SPACING_PX
    profile = np.bincount(r, ac.ravel())[: hi + 2] / np.bincount(r)[: hi + 2]
    for k in range(lo, hi + 1):
        if profile[k] >= profile[k - 1] and profile[k] > profile[k + 1]:
            return float(k)
    return math.nan


def mean_stats(rows: list[dict]) -> dict:
    out = {}
    for key in rows[0]:
        values = np.array([np.nan if r[key] is None else r[key] for r in rows], np.float64)
        mean = np.nanmean(values, 0) if not np.isnan(values).all() else values.mean(0)
        out[key] = None if np.isnan(mean).all() else np.round(mean, 3).tolist()
    return out


def family_frames(family: str | None, seed: int, pre: Preprocessor) -> tuple[np.ndarray, ...]:
    """Sensor-space (256, 256, 3) RGB frames of one pouch at rest and pressed, each a raw
    fisheye frame through ``pre``. family None: the reference look."""
    base = SimConfig(image_size_px=SIZE)
    cfg = base if family is None else sample_look(np.random.default_rng(seed), family, base).config
    sim = PouchSimulator(cfg, seed)
    sim.step(DT, (0.0, 0.0), -1.0)
    rest = pre(sim.render_raw())
    for _ in range(int(PRESS_S / DT)):
        sim.step(DT, PRESS_XY_MM, PRESS_DEPTH_MM)
    return rest, pre(sim.render_raw())


def photo_frames(folder: Path, pattern: str) -> list[tuple[str, np.ndarray]]:
    """(name, sensor-space RGB image) of every photo matching ``pattern``."""
    out = []
    for path in sorted(folder.glob(pattern)):
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SystemExit(f"{path}: not an image OpenCV can read")
        pre = Preprocessor.reference(bgr.shape[:2], SIZE, interpolation="linear")
        out.append((path.name, pre(bgr)))
    return out


def render_speed(pouches: int, frames: int = 200, repeats: int = 5) -> dict:
    """Frames per CPU-second at 64 px: the reference look and each family (mean of pouches).

    Every renderer is timed once per round, rounds interleaved, best of ``repeats``
    rounds each (on a shared machine, a slow spell then hits every look alike).
    """

    def setup(cfg: SimConfig):
        session = SimulatedSession(cfg, 0, render=False)
        views = [session.simulator.view() for _ in itertools.islice(session, frames)]
        sim = PouchSimulator(cfg, 0)
        sim.render()
        renderer = sim._renderer
        for view in views:  # warm-up: fill the sprite cache
            renderer.render(view)
        return renderer, views

    base = SimConfig(image_size_px=64)
    cases = {"reference": [base]}
    for family in FAMILY_NAMES:
        cases[family] = [
            sample_look(np.random.default_rng(s), family, base).config for s in range(pouches)
        ]
    ready = {name: [setup(c) for c in configs] for name, configs in cases.items()}
    best = {name: [math.inf] * len(r) for name, r in ready.items()}
    for _ in range(repeats):
        for name, renderers in ready.items():
            for k, (renderer, views) in enumerate(renderers):
                c0 = time.process_time()
                for view in views:
                    renderer.render(view)
                best[name][k] = min(best[name][k], time.process_time() - c0)
    return {name: round(frames / float(np.mean(t))) for name, t in best.items()}


def label(tile: np.ndarray, text: str) -> np.ndarray:
    tile = tile.copy()
    cv2.rectangle(tile, (0, 0), (8 + 7 * len(text), 16), (0, 0, 0), -1)
    cv2.putText(
        tile, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1, cv2.LINE_AA
    )
    return tile


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--photos", type=Path, required=True, help="folder of real sensor photos")
    p.add_argument("--photos-glob", default="test*.jpg", help="photos that show beads")
    p.add_argument("--pouches", type=int, default=3, help="pouches measured per family")
    p.add_argument("--image", type=Path, default=None, help="write the picture grid here")
    p.add_argument("--speed", action="store_true", help="also time rendering at 64 px")
    args = p.parse_args(argv)

    photos = photo_frames(args.photos, args.photos_glob)
    if not photos:
        raise SystemExit(f"{args.photos}: no photos match {args.photos_glob!r}")
    pre = Preprocessor.reference(output_size=SIZE, interpolation="linear")
    per_photo = {name: image_stats(im, grid_mask(im)) for name, im in photos}
    rows: dict[str, dict] = {"real": mean_stats(list(per_photo.values()))}
    pictures: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for family in (None, *FAMILY_NAMES):
        name = family or "reference"
        frames = [family_frames(family, seed, pre) for seed in range(args.pouches)]
        rows[name] = mean_stats([image_stats(rest) for rest, _ in frames])
        pictures[name] = frames[0]

    split_of = {f: s for s, fams in LOOK_SPLITS.items() for f in fams}
    print(
        f"{'look':<12} {'split':<8} {'mean RGB':<16} {'std RGB':<12} {'bead px':>7} "
        f"{'blob px':>7} {'rim':>6}"
    )
    for name, r in rows.items():
        split = split_of.get(name, "photo" if name == "real" else "default")
        mean = "/".join(f"{v:.0f}" for v in r["mean_rgb"])
        std = "/".join(f"{v:.0f}" for v in r["std_rgb"])
        bead = "-" if r["bead_px"] is None else f"{r['bead_px']:.1f}"
        print(
            f"{name:<12} {split:<8} {mean:<16} {std:<12} {bead:>7} "
            f"{r['blob_px']:>7.1f} {r['rim_contrast']:>6.3f}"
        )

    if args.image is not None:
        grid = []
        for k, (name, (rest, pressed)) in enumerate(pictures.items()):
            photo_name, photo = photos[k % len(photos)]
            tiles = [
                label(cv2.resize(rest, (TILE_PX, TILE_PX), interpolation=cv2.INTER_AREA), name),
                label(
                    cv2.resize(pressed, (TILE_PX, TILE_PX), interpolation=cv2.INTER_AREA), "pressed"
                ),
                label(
                    cv2.resize(photo, (TILE_PX, TILE_PX), interpolation=cv2.INTER_AREA),
                    f"real: {Path(photo_name).stem}",
                ),
            ]
            grid.append(np.concatenate(tiles, axis=1))
        args.image.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.image), cv2.cvtColor(np.concatenate(grid), cv2.COLOR_RGB2BGR))

    result = {
        "size_px": SIZE,
        "pouches": args.pouches,
        "photos": [n for n, _ in photos],
        "splits": {k: list(v) for k, v in LOOK_SPLITS.items()},
        "stats": rows,
        "photo_stats": per_photo,
    }
    if args.speed:
        from beadsight.inference.machine import cpu_name

        speed = render_speed(args.pouches)
        result["speed_64px_frames_per_cpu_s"] = speed
        result["slowdown_vs_reference"] = {
            k: round(speed["reference"] / v, 2) for k, v in speed.items()
        }
        result["cpu"] = cpu_name()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
