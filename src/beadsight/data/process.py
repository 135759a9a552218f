"""Raw recording -> dataset: clock alignment, per-frame labels, preprocessing, QA summary.

:func:`process_recording` reads a raw session of either format
(:mod:`beadsight.data.recording`) and writes a dataset
(:class:`beadsight.data.dataset.DatasetWriter`, which also segments presses):

* **Clocks.** Frames, scale readings and printer commands are all stamped by the
  host. When every stream carries the monotonic clock (this project's format) it is
  used for alignment (it never jumps with NTP); otherwise unix time (reference
  format). Dataset timestamps are unix seconds (float64).
* **Force per frame** by interpolating the scale log at each frame time:
  ``"pchip"`` (default; a shape-preserving piecewise cubic: no overshoot or ringing
  around the sharp onset of a press, never below the smallest neighbouring
  reading), ``"cubic"`` (an interpolating cubic spline, like the reference) or
  ``"linear"``. Never extrapolated: frames before the first or after the last
  reading are invalid, and so are frames inside a gap of more than
  ``max_force_gap_s`` between readings.
* **Position per frame**: zero-order hold of the last executed printer command
  (its XY in mm from the sensor centre). Frames before the first command, or
  whose last command is not a data move (homing, parking; x = y = -1 in the
  reference log), are invalid.
* **Images**: streamed chunk by chunk through a :class:`~beadsight.preprocess.Preprocessor`
  on a thread pool (OpenCV releases the GIL); for MJPG video the JPEGs are decoded
  by the workers, at reduced size when the output does not need full resolution,
  so memory stays bounded whatever the recording length.
* **QA**: ``<dataset>.qa.json`` (presses, dropped frames, force range, invalid
  frames and why) and ``<dataset>.qa.png`` (press coverage map, force trace).
"""

from __future__ import annotations

import collections
import json
import logging
import os
import queue
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from beadsight.config import ConfigError, SensorGeometry, _Serializable
from beadsight.data.dataset import DatasetWriter, open_dataset
from beadsight.data.recording import Recording, RecordingError, iter_video, open_recording
from beadsight.preprocess import Preprocessor

logger = logging.getLogger(__name__)

FORCE_INTERPOLATIONS = ("pchip", "cubic", "linear")
DECODE_FLAGS = {
    1: cv2.IMREAD_COLOR,
    2: cv2.IMREAD_REDUCED_COLOR_2,
    4: cv2.IMREAD_REDUCED_COLOR_4,
    8: cv2.IMREAD_REDUCED_COLOR_8,
}
DROP_GAP_FRAMES = 1.5  # a gap between frame times above this many frame periods is a drop

# Reasons a frame is invalid (one per frame; the first that applies, in this order).
REASONS = (
    "before_force_log",
    "after_force_log",
    "force_gap",
    "no_printer_log",
    "before_first_move",
    "non_data_move",
)


@dataclass(frozen=True)
class ProcessConfig(_Serializable):
    """How a raw recording becomes a dataset."""

    image_size: int = 256  # side of the dataset's square images, px
    preprocess: str = "reference"  # "reference", "none", or a fisheye calibration .json path
    interpolation: str = "linear"  # reference unwarp sampling: "linear" or "reference" (bit-exact)
    resize: str = "supersample"  # "supersample" (fast, antialiased), "area", "linear"
    force_interpolation: str = "pchip"  # "pchip", "cubic" (reference) or "linear"
    max_force_gap_s: float = 0.5  # frames inside a longer gap between scale readings are invalid
    camera_delay_s: float = 0.0  # capture-to-timestamp latency subtracted from frame times
    decode_scale: int = 0  # JPEG decode reduction 1, 2, 4, 8; 0 = largest that keeps detail
    workers: int = 0  # preprocessing threads; 0 = one per CPU core
    batch_frames: int = 64  # frames per dataset append
    compression: str | None = None  # HDF5 compression of frames ("gzip", "lzf", None)

    def __post_init__(self) -> None:
        if int(self.image_size) != self.image_size or self.image_size < 8:
            raise ConfigError(f"image_size must be an integer >= 8, got {self.image_size}")
        if self.force_interpolation not in FORCE_INTERPOLATIONS:
            raise ConfigError(
                f"force_interpolation must be one of {FORCE_INTERPOLATIONS}, got "
                f"{self.force_interpolation!r}"
            )
        if not self.max_force_gap_s > 0:
            raise ConfigError(f"max_force_gap_s must be > 0, got {self.max_force_gap_s}")
        if self.decode_scale not in (0, *DECODE_FLAGS):
            raise ConfigError(
                f"decode_scale must be 0 (auto), 1, 2, 4 or 8, got {self.decode_scale}"
            )
        if self.workers < 0 or self.batch_frames < 1:
            raise ConfigError("workers must be >= 0 and batch_frames >= 1")
        if self.compression not in (None, "gzip", "lzf"):
            raise ConfigError(f"compression must be gzip, lzf or None, got {self.compression!r}")


# --- per-frame labels ------------------------------------------------------------------------
def _strictly_increasing(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort by time and average readings that share a timestamp."""
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    uniq, inverse, counts = np.unique(t, return_inverse=True, return_counts=True)
    if len(uniq) == len(t):
        return t, values
    sums = np.bincount(inverse, weights=values, minlength=len(uniq))
    return uniq, sums / counts


def interpolate_force(
    t_force: np.ndarray,
    force_n: np.ndarray,
    t_frames: np.ndarray,
    *,
    method: str = "pchip",
    max_gap_s: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Force at each frame time; never extrapolates.

    t_force: (M,) s; force_n: (M,) N; t_frames: (N,) s (same clock).
    returns: force (N,) float64 N (NaN where invalid) and a reason code (N,) int8:
    0 valid, 1 before the first reading, 2 after the last, 3 inside a gap longer
    than ``max_gap_s``.
    """
    from scipy.interpolate import CubicSpline, PchipInterpolator

    t_frames = np.asarray(t_frames, np.float64)
    force = np.full(len(t_frames), np.nan)
    reason = np.zeros(len(t_frames), np.int8)
    ok = np.isfinite(t_force) & np.isfinite(force_n)
    t, f = _strictly_increasing(
        np.asarray(t_force, np.float64)[ok], np.asarray(force_n, np.float64)[ok]
    )
    if len(t) < 2:
        reason[:] = 1
        return force, reason
    reason[t_frames < t[0]] = 1
    reason[t_frames > t[-1]] = 2
    inside = reason == 0
    idx = np.clip(np.searchsorted(t, t_frames[inside], side="right"), 1, len(t) - 1)
    gap = (t[idx] - t[idx - 1]) > max_gap_s
    inside_idx = np.flatnonzero(inside)
    reason[inside_idx[gap]] = 3
    good = reason == 0
    if method == "linear":
        force[good] = np.interp(t_frames[good], t, f)
    elif method == "cubic":
        force[good] = CubicSpline(t, f, extrapolate=False)(t_frames[good])
    elif method == "pchip":
        force[good] = PchipInterpolator(t, f, extrapolate=False)(t_frames[good])
    else:
        raise ValueError(f"method must be one of {FORCE_INTERPOLATIONS}, got {method!r}")
    return force, reason


def hold_positions(
    t_moves: np.ndarray, offset_mm: np.ndarray, is_data: np.ndarray, t_frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order hold of the last executed command's XY at each frame time.

    t_moves: (K,) s; offset_mm: (K, 2) mm from the sensor centre; is_data: (K,) bool.
    returns: position (N, 2) float64 mm (NaN where invalid) and a reason code (N,) int8:
    0 valid, 1 no printer log, 2 before the first command, 3 the last command is not
    a data move. A command exactly at a frame's time counts as executed.
    """
    n = len(t_frames)
    position = np.full((n, 2), np.nan)
    reason = np.zeros(n, np.int8)
    if len(t_moves) == 0:
        reason[:] = 1
        return position, reason
    order = np.argsort(t_moves, kind="stable")
    t, xy, data = t_moves[order], offset_mm[order], np.asarray(is_data, bool)[order]
    idx = np.searchsorted(t, t_frames, side="right") - 1
    reason[idx < 0] = 2
    has = idx >= 0
    held = idx[has]
    ok_data = data[held] & np.isfinite(xy[held]).all(axis=1)
    rows = np.flatnonzero(has)
    reason[rows[~ok_data]] = 3
    position[rows[ok_data]] = xy[held[ok_data]]
    return position, reason


@dataclass
class FrameLabels:
    """Per logged frame (recording order): t_unix (N,) s, force_n (N,) N, position_mm
    (N, 2) mm, valid (N,) bool, reason (N,) int8 index+1 into REASONS (0 = valid)."""

    t_unix: np.ndarray
    force_n: np.ndarray
    position_mm: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    clock: str


def frame_labels(rec: Recording, config: ProcessConfig = ProcessConfig()) -> FrameLabels:
    """Align the streams of ``rec`` and label every logged frame."""
    clock = "monotonic" if rec.has_monotonic else "unix"
    key = "t_mono" if clock == "monotonic" else "t_unix"
    t_frames = getattr(rec.frames, key) - config.camera_delay_s
    force, f_reason = interpolate_force(
        getattr(rec.force, key),
        rec.force.force_n,
        t_frames,
        method=config.force_interpolation,
        max_gap_s=config.max_force_gap_s,
    )
    position, p_reason = hold_positions(
        getattr(rec.moves, key), rec.moves.offset_mm, rec.moves.is_data, t_frames
    )
    reason = np.where(f_reason > 0, f_reason, np.where(p_reason > 0, p_reason + 3, 0))
    valid = reason == 0  # force stays known (not NaN) where only the position is missing
    return FrameLabels(
        rec.frames.t_unix - config.camera_delay_s,
        force,
        position,
        valid,
        reason.astype(np.int8),
        clock,
    )


# --- streaming images -------------------------------------------------------------------
_END = object()


def _producer(
    rec: Recording,
    order: np.ndarray,
    packets: bool,
    out: queue.Queue,
    stats: dict[str, int],
    stop: threading.Event,
) -> None:
    """Put (row, payload) for every logged frame found in the videos, in ``order``."""
    try:
        chunks = rec.frames.chunk[order]
        bounds = np.flatnonzero(np.diff(chunks)) + 1
        for rows in np.split(order, bounds):
            if not len(rows) or stop.is_set():
                continue
            chunk = int(rec.frames.chunk[rows[0]])
            by_index = {int(rec.frames.index[r]): int(r) for r in rows}
            video = rec.videos.get(chunk)
            if video is None:
                stats["missing_video"] += len(rows)
                continue
            seen = 0
            for i, payload in enumerate(iter_video(video, packets=packets)):
                if stop.is_set():
                    return
                row = by_index.get(i)
                if row is None:
                    stats["unlogged_video"] += 1
                    continue
                seen += 1
                out.put((row, payload))
            if seen < len(rows):
                stats["missing_video"] += len(rows) - seen
                rec.warnings.append(
                    f"{video.name}: {len(rows) - seen} logged frame(s) missing from the video "
                    "(truncated chunk); skipped"
                )
        out.put(_END)
    except BaseException as e:  # noqa: BLE001 - handed to the consumer
        out.put(e)


def _make_worker(pre: Preprocessor, packets: bool, flag: int):
    def work(payload: np.ndarray) -> np.ndarray | None:
        image = cv2.imdecode(payload, flag) if packets else payload
        if image is None:  # a corrupt or truncated JPEG (e.g. the last frame of a crash)
            return None
        return pre(image)

    return work


def _choose_decode(
    rec: Recording, pre: Preprocessor, config: ProcessConfig
) -> tuple[bool, int, Preprocessor]:
    first = next(iter(rec.videos.values()), None)
    if first is None:
        return False, 1, pre
    try:
        sample = next(iter_video(first, packets=True))
    except (RecordingError, StopIteration):
        return False, 1, pre  # not MJPG (e.g. XVID): decode whole frames
    factor = config.decode_scale or pre.max_reduction()
    if factor > 1:
        try:
            reduced = pre.for_reduced_input(factor)
        except ValueError as e:
            if config.decode_scale:
                raise ConfigError(f"decode_scale={factor}: {e}") from None
            factor, reduced = 1, pre
        probe = cv2.imdecode(sample, DECODE_FLAGS[factor])
        if probe is None or probe.shape[:2] != reduced.input_hw:
            factor, reduced = 1, pre
        pre = reduced
    return True, factor, pre


def _input_hw(rec: Recording) -> tuple[int, int]:
    if rec.frame_hw is not None:
        return rec.frame_hw
    for video in rec.videos.values():
        for image in iter_video(video):
            return image.shape[:2]
    raise RecordingError(f"{rec.path}: no readable video frames")


# --- the whole pass ----------------------------------------------------------------------
def process_recording(
    raw: str | Path,
    out: str | Path,
    config: ProcessConfig = ProcessConfig(),
    *,
    geometry: SensorGeometry | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Process raw session ``raw`` into dataset ``out`` (HDF5); returns the QA summary.

    Also writes ``<out>.qa.json`` and ``<out>.qa.png`` next to the dataset.
    """
    started = time.perf_counter()
    raw, out = Path(raw), Path(out)
    rec = open_recording(raw)
    if len(rec.frames) == 0:
        raise RecordingError(f"{raw}: the frame log is empty; nothing to process")
    if not rec.videos:
        raise RecordingError(f"{raw}: no video files found")
    geometry = (geometry or _recording_geometry(rec)).with_image_size(config.image_size)
    labels = frame_labels(rec, config)
    pre = Preprocessor.from_spec(
        config.preprocess,
        _input_hw(rec),
        config.image_size,
        interpolation=config.interpolation,
        resize=config.resize,
    )
    packets, factor, pre_used = _choose_decode(rec, pre, config)
    order = np.lexsort((rec.frames.index, rec.frames.chunk))
    stats = {"missing_video": 0, "unlogged_video": 0, "undecodable": 0}
    written = _stream(
        rec,
        order,
        labels,
        pre_used,
        packets,
        factor,
        config,
        geometry,
        out,
        stats,
        progress,
        provenance={
            "source": "beadsight process",
            "raw": str(raw),
            "raw_format": rec.format,
            "process": config.to_dict(),
            "preprocess": pre_used.to_dict(),
            "decode_scale": factor,
            "clock": labels.clock,
        },
    )
    elapsed = time.perf_counter() - started
    qa = quality_summary(rec, labels, out, stats, written, elapsed, pre_used, factor, config)
    write_qa(out, qa)
    return qa


def _recording_geometry(rec: Recording) -> SensorGeometry:
    meta = rec.metadata.get("geometry")
    if isinstance(meta, dict):
        return SensorGeometry.from_dict(meta)
    params = rec.metadata.get("experiment_parameters", {})
    kwargs = {}
    if "sensor_size" in params:
        kwargs["sensor_size_mm"] = float(np.asarray(params["sensor_size"]).reshape(-1)[0])
    if "contact_radius" in params:
        kwargs["finger_radius_mm"] = float(params["contact_radius"])
    if "radius" in params:
        kwargs["press_range_mm"] = float(params["radius"])
    return SensorGeometry(**kwargs)


def _stream(
    rec, order, labels, pre, packets, factor, config, geometry, out, stats, progress, provenance
) -> int:
    workers = config.workers or os.cpu_count() or 1
    inflight_max = workers * 4
    q: queue.Queue = queue.Queue(maxsize=inflight_max * 2)
    stop = threading.Event()
    producer = threading.Thread(
        target=_producer,
        args=(rec, order, packets, q, stats, stop),
        daemon=True,
        name="beadsight-process-reader",
    )
    work = _make_worker(pre, packets, DECODE_FLAGS[factor])
    threads_before = cv2.getNumThreads()
    cv2.setNumThreads(1)  # parallelism comes from the pool; avoid oversubscription
    pending: collections.deque[tuple[int, Future]] = collections.deque()
    batch_rows: list[int] = []
    batch_images: list[np.ndarray] = []
    written = 0

    def flush_batch(writer: DatasetWriter) -> None:
        nonlocal written
        if not batch_rows:
            return
        rows = np.asarray(batch_rows)
        writer.append(
            np.stack(batch_images),
            labels.force_n[rows],
            labels.position_mm[rows],
            labels.valid[rows],
            labels.t_unix[rows],
        )
        written += len(rows)
        batch_rows.clear()
        batch_images.clear()

    bar = tqdm(total=len(order), unit="frame", desc="process", disable=not progress)
    try:
        with (
            ThreadPoolExecutor(max_workers=workers, thread_name_prefix="beadsight-pre") as pool,
            DatasetWriter(
                out,
                geometry,
                channel_order=pre.channel_order,
                fps=rec.fps,
                provenance=provenance,
                compression=config.compression,
            ) as writer,
        ):
            producer.start()
            done = False
            while not done or pending:
                while not done and len(pending) < inflight_max:
                    item = q.get()
                    if item is _END:
                        done = True
                    elif isinstance(item, BaseException):
                        raise item
                    else:
                        row, payload = item
                        pending.append((row, pool.submit(work, payload)))
                if pending:
                    row, fut = pending.popleft()
                    image = fut.result()
                    bar.update(1)
                    if image is None:
                        stats["undecodable"] += 1
                        continue
                    batch_rows.append(row)
                    batch_images.append(image)
                    if len(batch_rows) >= config.batch_frames:
                        flush_batch(writer)
            flush_batch(writer)
    finally:
        stop.set()
        while producer.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                producer.join(timeout=0.05)
        cv2.setNumThreads(threads_before)
        bar.close()
    if stats["undecodable"]:
        rec.warnings.append(
            f"{stats['undecodable']} video frame(s) could not be decoded "
            "(corrupt or truncated JPEG); skipped"
        )
    return written


# --- QA -----------------------------------------------------------------------------------
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
    json_path.write_text(json.dumps(qa, indent=2, default=str))
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
    ax.add_patch(
        Rectangle(
            (-half, -half),
            2 * half,
            2 * half,
            fill=False,
            ls="--",
            lw=0.8,
            color="0.5",
            label="field of view",
        )
    )
    ax.add_patch(
        Rectangle(
            (-reach, -reach),
            2 * reach,
            2 * reach,
            fill=False,
            ls=":",
            lw=0.8,
            color="tab:blue",
            label="press range",
        )
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
    fig.savefig(path, dpi=100)
    return path
