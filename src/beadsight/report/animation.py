"""The animation of one press (GIF): camera frame | true map | predicted map, and its caption.

:func:`animation_frames` runs a model over consecutive frames around one press of a
dataset; :func:`write_animation` draws them as a looping GIF (written atomically:
a full disk raises :class:`~beadsight.files.WriteError`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.errors import BeadSightError
from beadsight.files import atomic_write
from beadsight.report.plots import MAP_AXES, MIN_COLOUR_RANGE_KPA, PRESSURE_CMAP

ANIMATION_MARGIN_FRAMES = 12  # frames shown before contact begins and after it ends
ANIMATION_PANEL_PX = 192  # side of each panel of the animation
ANIMATION_TEXT_PX = 22  # height of the title strip above and the footer below the panels
ANIMATION_COLOUR_PERCENTILE = 99.9  # of the predicted maps: the colour scale's top


def animation_frames(
    model: PressureModel, data: Path, press: int, batch_size: int, count: int
) -> dict:
    """Consecutive frames around one press's contact: camera RGB, true and predicted maps.

    returns {"index": (K,), "frames": (K, S, S, 3) uint8, "gt": (K, S, S) kPa,
    "pred": (K, S, S) kPa, "time_s": (K,), "force_gt_n", "force_pred_n": (K,)}.
    """
    from beadsight.data.dataset import open_dataset
    from beadsight.data.labels import label_maps
    from beadsight.data.splits import dataset_window_ends
    from beadsight.data.windows import WindowReader
    from beadsight.geometry import total_force_n

    rest = bool(model.rest)
    with open_dataset(data) as ds:
        start, stop = (int(v) for v in ds.presses[press])
        ends = dataset_window_ends(ds, model.span, np.array([press]), rest=rest)
        lo, hi = start - ANIMATION_MARGIN_FRAMES, stop + ANIMATION_MARGIN_FRAMES
        ends = ends[(ends >= lo) & (ends < hi)][:count]
        if ends.size == 0:
            raise BeadSightError(
                f"{data}: press {press} has no frame that ends a full window"
                + (" with a rest image before it" if rest else "")
            )
        reader = WindowReader(ds, model.span, rest=rest)
        frames, pred = [], []
        for i in range(0, ends.size, batch_size):
            inputs = reader(ends[i : i + batch_size])  # (B, inputs, S, S, 3)
            frames.append(inputs[:, -1].copy())  # each window's newest frame
            pred.append(model.predict(inputs, batch_size=batch_size))
        pred = np.concatenate(pred)
        gt = label_maps(ds.force_n[ends], ds.position_mm[ends], ds.contact[ends], ds.geometry)
        geometry = ds.geometry
        time_s = ds.timestamp_s[ends] - ds.timestamp_s[ends[0]]
    return {
        "index": ends,
        "frames": np.concatenate(frames),
        "gt": gt,
        "pred": pred,
        "time_s": time_s,
        "force_gt_n": total_force_n(gt, geometry),
        "force_pred_n": total_force_n(pred, geometry),
    }


def strongest_press(data: Path, model: PressureModel) -> int:
    """Index of the press of ``data`` with the highest peak force, of those with a frame
    that ``model`` can predict (a full window, and a rest image for a rest-referenced one)."""
    from beadsight.data.dataset import open_dataset
    from beadsight.data.splits import dataset_window_ends

    with open_dataset(data) as ds:
        ds.require_presses()
        ends = dataset_window_ends(ds, model.span, rest=bool(model.rest))
        usable = np.isin(np.arange(ds.num_presses), ds.press_id[ends])
        if not usable.any():
            raise BeadSightError(f"{data}: no press has a frame that {model.source} can predict")
        peaks = [ds.force_n[a:b].max() for a, b in ds.presses]
    return int(np.argmax(np.where(usable, peaks, -np.inf)))


def colourise(maps_kpa: np.ndarray, vmax_kpa: float) -> np.ndarray:
    """(..., H, W) kPa -> (..., H, W, 3) uint8 RGB with the pressure colour map, 0..vmax."""
    from matplotlib import colormaps

    lut = (colormaps[PRESSURE_CMAP](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    index = np.clip(maps_kpa / max(vmax_kpa, 1e-6) * 255, 0, 255).astype(np.uint8)
    return lut[index]


def _text_strip(width: int, text: str) -> np.ndarray:
    strip = np.full((ANIMATION_TEXT_PX, width, 3), 255, np.uint8)
    cv2.putText(strip, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return strip


def _panel(image: np.ndarray, title: str) -> np.ndarray:
    """Upscale an (S, S, 3) RGB image to the panel size and put a title above it."""
    px = ANIMATION_PANEL_PX
    interp = cv2.INTER_NEAREST if image.shape[0] <= px else cv2.INTER_AREA
    return np.vstack([_text_strip(px, title), cv2.resize(image, (px, px), interpolation=interp)])


def animation_colour_max(gt_kpa: np.ndarray, pred_kpa: np.ndarray) -> float:
    """Top of the animation's colour scale, kPa: the true maximum or the predicted 99.9th
    percentile, whichever is larger (one stray predicted pixel does not wash it out)."""
    top = max(float(gt_kpa.max()), float(np.percentile(pred_kpa, ANIMATION_COLOUR_PERCENTILE)))
    return max(top, MIN_COLOUR_RANGE_KPA)


def write_animation(clip: dict, path: str | Path, fps: float) -> Path:
    """One press as a looping GIF at ``fps``: camera frame | true map | predicted map.

    clip: {"frames": (K, S, S, 3) uint8 RGB, "gt", "pred": (K, S, S) kPa, "time_s": (K,) s,
    "force_gt_n", "force_pred_n": (K,) N} (``beadsight.demo.animation_frames``).
    """
    from PIL import Image

    vmax = animation_colour_max(clip["gt"], clip["pred"])
    gt_rgb, pred_rgb = colourise(clip["gt"], vmax), colourise(clip["pred"], vmax)
    images = []
    for k in range(len(clip["frames"])):
        row = np.hstack(
            [
                _panel(clip["frames"][k], "camera (sensor space)"),
                _panel(gt_rgb[k], f"true  {clip['force_gt_n'][k]:5.1f} N"),
                _panel(pred_rgb[k], f"predicted  {clip['force_pred_n'][k]:5.1f} N"),
            ]
        )
        text = f"t = {clip['time_s'][k]:4.2f} s   colour: 0 .. {vmax:.0f} kPa ({PRESSURE_CMAP})"
        images.append(Image.fromarray(np.vstack([row, _text_strip(row.shape[1], text)])))
    return atomic_write(
        path,
        lambda f: images[0].save(
            f,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=round(1000 / fps),
            loop=0,
        ),
    )


def animation_caption(fps: float, vmax_kpa: float) -> str:
    return (
        "One press, frame by frame: the camera image the model reads (left), the true "
        f"pressure map (middle) and the predicted one (right), at {fps:g} frames/s; the "
        "titles give the true and predicted total force in N, the footer the time from the "
        f"first shown frame. Colour: pressure from 0 kPa (dark purple) to {vmax_kpa:.0f} kPa "
        f"(yellow), {PRESSURE_CMAP}, the same scale in both maps. {MAP_AXES}"
    )
