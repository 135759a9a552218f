"""The demo's report folder: the animation of one press, ``index.html`` and ``demo.json``."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.demo.config import (
    ANIMATION_HEADER_PX,
    ANIMATION_MARGIN_FRAMES,
    ANIMATION_MAX_FRAMES,
    ANIMATION_PANEL_PX,
    INDEX_FILE,
    MARKER,
    DemoError,
)
from beadsight.files import atomic_write_text


def prepare_out_dir(out: Path) -> None:
    """Create ``out``; refuse a non-empty folder that is not an earlier demo report."""
    if out.exists() and not out.is_dir():
        raise DemoError(f"{out}: exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise DemoError(
            f"{out}: folder exists, is not empty and is not a beadsight demo report "
            f"(no {MARKER}); choose another --out"
        )
    out.mkdir(parents=True, exist_ok=True)


def _colourise(maps_kpa: np.ndarray, vmax_kpa: float) -> np.ndarray:
    """(..., H, W) kPa -> (..., H, W, 3) uint8 RGB with the viridis colour map, 0..vmax."""
    from matplotlib import colormaps

    lut = (colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    index = np.clip(maps_kpa / max(vmax_kpa, 1e-6) * 255, 0, 255).astype(np.uint8)
    return lut[index]


def _panel(image: np.ndarray, title: str) -> np.ndarray:
    """Upscale an (S, S, 3) RGB image to the panel size and put a title above it."""
    px = ANIMATION_PANEL_PX
    interp = cv2.INTER_NEAREST if image.shape[0] <= px else cv2.INTER_AREA
    body = cv2.resize(image, (px, px), interpolation=interp)
    head = np.full((ANIMATION_HEADER_PX, px, 3), 255, np.uint8)
    cv2.putText(head, title, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([head, body])


def animation_frames(
    model: PressureModel, data: Path, press: int, batch_size: int, count: int = ANIMATION_MAX_FRAMES
) -> dict:
    """Consecutive frames around one press's contact: camera RGB, true and predicted maps.

    returns {"index": (K,), "frames": (K, S, S, 3) uint8, "gt": (K, S, S) kPa,
    "pred": (K, S, S) kPa, "time_s": (K,), "force_gt_n", "force_pred_n": (K,)}.
    """
    from beadsight.data.dataset import open_dataset
    from beadsight.data.labels import label_maps
    from beadsight.data.splits import dataset_window_ends
    from beadsight.geometry import total_force_n

    with open_dataset(data) as ds:
        start, stop = (int(v) for v in ds.presses[press])
        ends = dataset_window_ends(ds, model.span, np.array([press]))
        lo, hi = start - ANIMATION_MARGIN_FRAMES, stop + ANIMATION_MARGIN_FRAMES
        ends = ends[(ends >= lo) & (ends < hi)][:count]
        if ends.size == 0:
            raise DemoError(f"{data}: press {press} has no frame that ends a full window")
        first = int(ends[0]) - model.span + 1
        frames = ds.read_frames(first, int(ends[-1]) + 1)
        windows = np.stack([frames[e - first - model.span + 1 : e - first + 1] for e in ends])
        pred = model.predict(windows, batch_size=batch_size)
        gt = label_maps(ds.force_n[ends], ds.position_mm[ends], ds.contact[ends], ds.geometry)
        geometry = ds.geometry
        time_s = ds.timestamp_s[ends] - ds.timestamp_s[ends[0]]
    return {
        "index": ends,
        "frames": frames[ends - first],
        "gt": gt,
        "pred": pred,
        "time_s": time_s,
        "force_gt_n": total_force_n(gt, geometry),
        "force_pred_n": total_force_n(pred, geometry),
    }


def write_animation(clip: dict, path: Path, fps: float) -> Path:
    """Write ``clip`` (see :func:`animation_frames`) as a looping GIF at ``fps``."""
    from PIL import Image

    vmax = float(max(clip["gt"].max(), np.percentile(clip["pred"], 99.9), 1e-3))
    gt_rgb, pred_rgb = _colourise(clip["gt"], vmax), _colourise(clip["pred"], vmax)
    images = []
    for k in range(len(clip["index"])):
        row = np.hstack(
            [
                _panel(clip["frames"][k], "camera (sensor space)"),
                _panel(gt_rgb[k], f"true  {clip['force_gt_n'][k]:5.1f} N"),
                _panel(pred_rgb[k], f"predicted  {clip['force_pred_n'][k]:5.1f} N"),
            ]
        )
        foot = np.full((ANIMATION_HEADER_PX, row.shape[1], 3), 255, np.uint8)
        text = f"t = {clip['time_s'][k]:4.2f} s   colour: 0 .. {vmax:.0f} kPa (viridis)"
        cv2.putText(foot, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        images.append(Image.fromarray(np.vstack([row, foot])))
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(
        path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0
    )
    return path


def strongest_press(data: Path) -> int:
    from beadsight.data.dataset import open_dataset

    with open_dataset(data) as ds:
        ds.require_presses()
        peaks = [ds.force_n[a:b].max() for a, b in ds.presses]
    return int(np.argmax(peaks))


def write_index(out: Path, summary: dict, table: str) -> Path:
    """A self-contained index.html for the report folder."""
    files = summary.get("files", {})
    images = [
        name
        for name in ("animation.gif", "examples.png", "force_traces.png", "region_error.png")
        if name in files.values()
    ]
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in summary.get("notes", []))
    body = [
        "<!doctype html><meta charset='utf-8'><title>beadsight demo</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:2em auto}"
        "pre{background:#f4f4f4;padding:1em}img{max-width:100%}</style>",
        "<h1>beadsight demo</h1>",
        f"<p>{html.escape(summary['description'])}</p>",
        f"<pre>{html.escape(table)}</pre>",
        f"<ul>{notes}</ul>",
        *(
            [f"<h2>The shipped model</h2><pre>{html.escape(summary['model_record'])}</pre>"]
            if summary.get("model_record")
            else []
        ),
        *(f"<h2>{html.escape(name)}</h2><img src='{html.escape(name)}'>" for name in images),
        "<h2>Files</h2><ul>",
        *(
            f"<li><a href='{html.escape(f)}'>{html.escape(f)}</a>: {html.escape(k)}</li>"
            for k, f in sorted(files.items())
        ),
        "</ul>",
    ]
    return atomic_write_text(out / INDEX_FILE, "\n".join(body))


def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    """``demo.json``: what was run, seeds, timings (no NaN; written atomically)."""
    return atomic_write_text(
        out / MARKER, json.dumps(summary, indent=2, default=str, allow_nan=False)
    )
