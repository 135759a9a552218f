"""The QA summary of a processed recording: ``<dataset>.qa.json`` and ``<dataset>.qa.png``.

Counts and ranges a person checks before training on a dataset: presses and where
they were, dropped frames, force range, invalid frames and why, what was decoded
(the reference force counter) and every warning raised on the way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from beadsight.data.dataset import open_dataset
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.frame_labels import REASONS, FrameLabels
from beadsight.data.recording import Recording
from beadsight.files import atomic_write, atomic_write_json
from beadsight.preprocess import Preprocessor

DROP_GAP_FRAMES = 1.5  # a gap between frame times above this many frame periods is a drop


def quality_summary(
    rec: Recording,
    labels: FrameLabels,
    out: Path,
    stats: dict[str, int],
    written: int,
    elapsed_s: float,
    pre: Preprocessor,
    factor: int,
    config: ProcessConfig,
) -> dict[str, Any]:
    """Counts and ranges a person checks before training on a dataset."""
    cam = rec.frames.camera_index
    cam_ok = cam[cam >= 0]
    camera_gaps = (
        int(np.clip(np.diff(np.sort(cam_ok)) - 1, 0, None).sum()) if len(cam_ok) > 1 else 0
    )
    t = np.sort(rec.frames.t_unix)
    period = 1.0 / rec.fps
    time_gaps = np.diff(t)[np.diff(t) > DROP_GAP_FRAMES * period] if len(t) > 1 else np.array([])
    reasons = {name: int((labels.reason == k + 1).sum()) for k, name in enumerate(REASONS)}
    with open_dataset(out) as ds:
        presses = ds.presses
        press_xy = [ds.position_mm[a:b].mean(axis=0).tolist() for a, b in presses]
        press_peak = [float(np.nanmax(ds.force_n[a:b])) for a, b in presses]
        valid_force = ds.force_n[ds.valid]
        n_valid = int(ds.valid.sum())
        geometry = ds.geometry.to_dict()
        n_contact = int(ds.contact.sum())
    aborted = [e.get("press") for e in rec.events if e.get("event") == "press_abort"]
    return {
        "raw": str(rec.path),
        "raw_format": rec.format,
        "dataset": str(out),
        "frames_logged": int(len(rec.frames)),
        "frames_written": int(written),
        "frames_valid": n_valid,
        "frames_in_contact": n_contact,
        "invalid_frames": {k: v for k, v in reasons.items() if v},
        "dropped_frames": _dropped(camera_gaps, time_gaps, period, len(cam_ok) > 1, stats),
        "geometry": geometry,
        "presses": len(press_xy),
        "press_positions_mm": press_xy,
        "press_peak_force_n": press_peak,
        "aborted_presses": aborted,
        "force_n": {
            "min": float(np.min(valid_force)) if len(valid_force) else None,
            "max": float(np.max(valid_force)) if len(valid_force) else None,
            "readings": int(len(rec.force)),
        },
        "duration_s": float(t[-1] - t[0]) if len(t) > 1 else 0.0,
        "fps_nominal": rec.fps,
        "fps_measured": float((len(t) - 1) / (t[-1] - t[0]))
        if len(t) > 1 and t[-1] > t[0]
        else None,
        "clock": labels.clock,
        "force_interpolation": config.force_interpolation,
        "preprocess": pre.to_dict(),
        "decode_scale": factor,
        "processing_s": elapsed_s,
        "frames_per_s": written / elapsed_s if elapsed_s > 0 else None,
        "warnings": list(rec.warnings),
    }


def _dropped(
    camera_gaps: int, time_gaps: np.ndarray, period: float, has_index: bool, stats: dict[str, int]
) -> dict[str, int]:
    """Frames lost on the way; ``total`` counts each lost frame once. Capture losses show
    as timestamp gaps (frames the camera never delivered) and, when the recorder fell
    behind, also as gaps in the camera's frame counter: the larger of the two counts."""
    from_time = int(np.round(time_gaps / period - 1).clip(0).sum()) if len(time_gaps) else 0
    out = {
        "camera_index_gaps": camera_gaps,
        "time_gaps": from_time,
        "missing_from_video": int(stats["missing_video"]),
        "in_video_not_logged": int(stats["unlogged_video"]),
        "undecodable": int(stats["undecodable"]),
    }
    captured = max(camera_gaps, from_time) if has_index else from_time
    out["total"] = captured + out["missing_from_video"] + out["undecodable"]
    return out


def qa_paths(out: str | Path) -> tuple[Path, Path]:
    out = Path(out)
    return out.with_name(out.name + ".qa.json"), out.with_name(out.name + ".qa.png")


def write_qa(out: str | Path, qa: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``<out>.qa.json`` and the coverage plot ``<out>.qa.png``."""
    json_path, png_path = qa_paths(out)
    atomic_write_json(json_path, qa)
    plot_qa(qa, png_path)
    return json_path, png_path


def plot_qa(qa: dict[str, Any], path: Path) -> Path:
    """Coverage map of press locations (coloured by peak force) and frame counts."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    fig = Figure(figsize=(10, 4.5))
    FigureCanvasAgg(fig)
    ax, bx = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.1, 1]})
    xy = np.asarray(qa["press_positions_mm"], dtype=np.float64).reshape(-1, 2)
    peak = np.asarray(qa["press_peak_force_n"], dtype=np.float64)
    geometry = qa.get("geometry", {})
    half = float(geometry.get("sensor_size_mm", 41.0)) / 2
    reach = float(geometry.get("press_range_mm", 13.75))
    for side, ls, color, label in (
        (half, "--", "0.5", "field of view"),
        (reach, ":", "tab:blue", "press range"),
    ):
        corner, width = (-side, -side), 2 * side
        ax.add_patch(
            Rectangle(corner, width, width, fill=False, ls=ls, lw=0.8, color=color, label=label)
        )
    if len(xy):
        sc = ax.scatter(
            xy[:, 0], xy[:, 1], c=peak, cmap="viridis", s=28, edgecolors="k", linewidths=0.3
        )
        fig.colorbar(sc, ax=ax, label="peak force (N)")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_xlim(-half - 1, half + 1)
    ax.set_ylim(-half - 1, half + 1)
    ax.set_aspect("equal")
    ax.set_xlabel("x from sensor centre (mm, printer frame)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{qa['presses']} presses")
    dropped = {k: v for k, v in qa["dropped_frames"].items() if v and k != "total"}
    names = ["valid", *qa["invalid_frames"], *[f"dropped: {k}" for k in dropped]]
    values = [qa["frames_valid"], *qa["invalid_frames"].values(), *dropped.values()]
    bars = bx.barh(names, values, color=["tab:green"] + ["tab:red"] * (len(names) - 1))
    bx.bar_label(bars, fontsize=7, padding=2)
    bx.set_xlabel("frames")
    bx.set_title(f"{qa['frames_logged']} frames logged")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    return path
