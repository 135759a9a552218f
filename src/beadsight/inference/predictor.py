"""Streaming inference: one camera frame in, one pressure reading out.

:class:`PressurePredictor` owns a ring buffer of the last ``T`` frames (``T`` =
the checkpoint's window, 15 for the reference model) with their capture
timestamps, runs the model through a :mod:`beadsight.inference.runtimes` backend once the
window is full, and turns the kPa map into a :class:`Reading` (total force,
centre of pressure, contact mask and area).

Example::

    from beadsight import PressurePredictor

    predictor = PressurePredictor("best.pt")  # backend="auto": fastest accurate backend
    for frame_rgb, t in camera:  # (256, 256, 3) uint8 RGB, capture time in s
        reading = predictor.update(frame_rgb, t)
        if reading is not None:
            print(reading.force_n, reading.cop_mm)

Ring buffer
-----------
Frames are copied into a preallocated uint8 array of ``2 T`` slots: each frame is
written twice, at slots ``i`` and ``i + T``, so the last ``T`` frames are always
one contiguous, oldest-first view ``buffer[i + 1 : i + 1 + T]`` that goes to the
backend without any per-frame allocation or reordering.

Dropped frames
--------------
The frame period is ``1 / fps`` with ``fps`` from the checkpoint's provenance
(``provenance["fps"]``, or the training dataset's fps recorded there), else the
``fps`` argument, else 30 (the reference camera). For each new frame the number
of frames missing before it is ``round(dt * fps) - 1`` where ``dt`` is the time
since the previous frame (a gap under ``GAP_TOLERANCE`` periods counts as none:
camera jitter is not a drop).

* Gaps of up to ``max_gap_frames`` missing frames are counted in
  ``Reading.dropped_frames`` and the window simply continues: the model sees a
  slightly longer history, which it tolerates.
* Larger gaps are handled by ``on_gap``:

  - ``"reset"`` (default): the buffer is cleared and starts filling again from
    this frame; ``update`` returns ``None`` for the next ``T - 1`` frames. The
    model never sees a window that spans a long hole.
  - ``"hold"``: the missing frames are filled with copies of the last frame
    received (zero-order hold, at most ``T - 1`` of them), so readings continue
    at once.
  - ``"ignore"``: the drop is counted and the window continues.

Timestamps must increase strictly; a repeated or earlier timestamp is refused
with a ValueError (feeding the same frame twice is a capture bug).

Contact
-------
``contact_mask`` is ``pressure_kpa >= contact_threshold_kpa``: a fixed
threshold, by default the pressure of the release force of
:class:`~beadsight.config.ContactThresholds` (10 g) spread over the finger's
disk, about 0.8 kPa. It costs one comparison per pixel. ``contact_method="otsu"``
uses Otsu's threshold on the map instead (the evaluation's IoU definition),
applied only where the map has pressure above that same floor.
``has_contact`` is ``force_n >= contact_force_n`` (default: the 50 g contact force).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.config import ContactThresholds, SensorGeometry
from beadsight.geometry import disk_pressure_kpa

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0  # the reference camera's frame rate, used when the checkpoint names none
DEFAULT_MAX_GAP_FRAMES = 3  # missing frames tolerated before on_gap applies (100 ms at 30 fps)
GAP_TOLERANCE = 1.5  # dt below this many frame periods is jitter, not a dropped frame
GAP_POLICIES = ("reset", "hold", "ignore")
CONTACT_METHODS = ("threshold", "otsu")
OTSU_BINS = 256  # histogram bins for Otsu's threshold on the map


@dataclass(frozen=True)
class Reading:
    """One output of :meth:`PressurePredictor.update`.

    pressure_kpa: (H, W) float32 kPa, >= 0 (read-only array).
    force_n: total normal force, the integral of the map, N.
    cop_mm: (2,) float64 centre of pressure (x, y) in mm from the sensor centre,
        printer frame; NaN when the map has no pressure.
    has_contact: ``force_n >= contact_force_n``.
    contact_mask: (H, W) bool pixels in contact (see the module docstring).
    contact_area_mm2: area of ``contact_mask``, mm^2.
    timestamp_s: capture time of the newest frame of the window, s.
    latency_s: processing time from ``update`` being called to this reading, s.
    frame_index: index of the newest frame since the predictor was created or
        ``reset()`` (0-based, counts every frame passed to ``update``).
    dropped_frames: frames detected missing since creation or ``reset()``.
    """

    pressure_kpa: np.ndarray
    force_n: float
    cop_mm: np.ndarray
    has_contact: bool
    contact_mask: np.ndarray
    contact_area_mm2: float
    timestamp_s: float
    latency_s: float
    frame_index: int
    dropped_frames: int


def checkpoint_fps(model: PressureModel) -> float | None:
    """The camera rate the checkpoint's training data was recorded at, if it says."""
    meta = model.meta
    for source in (meta.provenance, meta.training):
        for value in (
            source.get("fps"),
            (source.get("dataset") or {}).get("fps")
            if isinstance(source.get("dataset"), dict)
            else None,
            source.get("dataset_fps"),
        ):
            try:
                fps = float(value) if value is not None else None
            except (TypeError, ValueError):
                fps = None
            if fps is not None and math.isfinite(fps) and fps > 0:
                return fps
    return None


class PressurePredictor:
    """Stateful frame-by-frame pressure estimation.

    model: a :class:`~beadsight.checkpoint.PressureModel` or a checkpoint path.
    backend: "auto" (fastest available backend that agrees with fp32 torch, see
        :func:`beadsight.inference.runtimes.select_backend`), "torch", "compile", "onnx",
        "openvino", "cuda", or a ready :class:`beadsight.inference.runtimes.Backend`.
    precision: "fp32", "bf16" or "auto" (let backend selection choose; with a
        named backend "auto" means fp32).
    device: torch device for the torch/compile/cuda backends (default: CUDA for
        "cuda", else CPU).
    fps: frame rate used for gap detection when the checkpoint records none.
    max_gap_frames, on_gap: dropped-frame policy (module docstring).
    contact_threshold_kpa, contact_method, contact_force_n: contact definitions.
    exported_model: path of an exported ``.onnx`` / OpenVINO ``.xml`` file to run
        with backend "onnx" or "openvino"; refused unless it was exported from
        this checkpoint.
    backend_options: extra keyword arguments for the backend (threads, cache_dir).

    Not thread-safe: call :meth:`update` from one thread (the live loop's).
    """

    def __init__(
        self,
        model: PressureModel | str | Path,
        backend: Any = "auto",
        precision: str = "auto",
        device: str | None = None,
        *,
        fps: float | None = None,
        max_gap_frames: int = DEFAULT_MAX_GAP_FRAMES,
        on_gap: str = "reset",
        contact_threshold_kpa: float | None = None,
        contact_method: str = "threshold",
        contact_force_n: float | None = None,
        exported_model: str | Path | None = None,
        backend_options: dict[str, Any] | None = None,
    ):
        from beadsight.inference.runtimes import Backend, create_backend

        if isinstance(model, (str, Path)):
            model = load_checkpoint(model)
        if on_gap not in GAP_POLICIES:
            raise ValueError(f"on_gap must be one of {GAP_POLICIES}, got {on_gap!r}")
        if contact_method not in CONTACT_METHODS:
            raise ValueError(
                f"contact_method must be one of {CONTACT_METHODS}, got {contact_method!r}"
            )
        if int(max_gap_frames) != max_gap_frames or max_gap_frames < 0:
            raise ValueError(f"max_gap_frames must be an integer >= 0, got {max_gap_frames}")
        self.model = model
        self.geometry: SensorGeometry = model.geometry
        self.window = model.window
        self.image_size = model.image_size
        fps_source = checkpoint_fps(model)
        self.fps = float(fps_source or fps or DEFAULT_FPS)
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.max_gap_frames = int(max_gap_frames)
        self.on_gap = on_gap
        self.contact_method = contact_method
        thresholds = ContactThresholds()
        self.contact_threshold_kpa = float(
            contact_threshold_kpa
            if contact_threshold_kpa is not None
            else disk_pressure_kpa(thresholds.release_n, self.geometry)
        )
        self.contact_force_n = float(
            contact_force_n if contact_force_n is not None else thresholds.contact_n
        )
        if isinstance(backend, Backend):
            self.backend = backend
        else:
            self.backend = create_backend(
                model,
                backend,
                precision=precision,
                device=device,
                exported_model=exported_model,
                **(backend_options or {}),
            )
        s, t = self.image_size, self.window
        self._frames = np.zeros((1, 2 * t, s, s, 3), dtype=np.uint8)  # doubled ring buffer
        self._times = np.zeros(2 * t, dtype=np.float64)
        self._reduction_cache()
        self.reset()

    # --- state ----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all buffered frames and counters; the next T-1 updates return None."""
        self._head = -1  # slot of the newest frame in [0, T)
        self._filled = 0  # valid frames in the window
        self._unseen = 0  # frames pushed since the backend last ran
        self._last_time: float | None = None
        self.frame_index = -1
        self.dropped_frames = 0
        self.gap_resets = 0

    @property
    def ready(self) -> bool:
        """True when the window holds T frames (the next update returns a reading)."""
        return self._filled >= self.window

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.fps

    def window_frames(self) -> np.ndarray:
        """The buffered window, (T, S, S, 3) uint8 RGB, oldest first (a read-only view).

        Only the newest ``min(filled, T)`` frames are meaningful before the buffer is full.
        """
        start = self._head + 1
        view = self._frames[0, start : start + self.window]
        view = view.view()
        view.flags.writeable = False
        return view

    def window_timestamps(self) -> np.ndarray:
        """(T,) float64 capture times of the window's frames, oldest first."""
        start = self._head + 1
        return self._times[start : start + self.window].copy()

    # --- input ----------------------------------------------------------------------
    def _check_frame(self, frame_rgb: np.ndarray) -> None:
        s = self.image_size
        shape = getattr(frame_rgb, "shape", None)
        dtype = getattr(frame_rgb, "dtype", None)
        if shape is None or len(shape) != 3 or shape[-1] != 3:
            raise ValueError(
                f"frame_rgb: expected a ({s}, {s}, 3) uint8 RGB frame for checkpoint "
                f"{self.model.source}, got shape {shape}"
            )
        if shape[:2] != (s, s):
            raise ValueError(
                f"frame_rgb: the source delivers {shape[0]}x{shape[1]} px frames but the "
                f"checkpoint {self.model.source} expects {s}x{s} px (its preprocessing output "
                f"size); preprocess the camera frames to {s}x{s}"
            )
        if dtype != np.uint8:
            raise ValueError(
                f"frame_rgb: expected dtype uint8 (0..255) {s}x{s}x3 RGB, got dtype {dtype}"
            )

    def _check_time(self, timestamp_s: float) -> float:
        t = float(timestamp_s)
        if not math.isfinite(t):
            raise ValueError(f"timestamp_s must be finite, got {timestamp_s}")
        if self._last_time is not None and t <= self._last_time:
            raise ValueError(
                f"timestamp_s must increase: got {t:.6f} s after {self._last_time:.6f} s "
                "(a repeated or reordered frame)"
            )
        return t

    def _missing_frames(self, t: float) -> int:
        if self._last_time is None:
            return 0
        periods = (t - self._last_time) * self.fps
        if periods < GAP_TOLERANCE:
            return 0
        return max(int(round(periods)) - 1, 1)

    def _push(self, frame_rgb: np.ndarray, t: float) -> None:
        head = (self._head + 1) % self.window
        self._frames[0, head] = frame_rgb
        self._frames[0, head + self.window] = frame_rgb
        self._times[head] = self._times[head + self.window] = t
        self._head = head
        self._filled = min(self._filled + 1, self.window)
        self._unseen += 1

    def _hold(self, copies: int) -> None:
        """Repeat the newest buffered frame ``copies`` times (zero-order hold)."""
        last = self._frames[0, self._head].copy()
        dt = self.frame_period_s
        t0 = self._last_time if self._last_time is not None else 0.0
        for k in range(min(copies, self.window - 1)):
            self._push(last, t0 + (k + 1) * dt)

    def _handle_gap(self, missing: int) -> None:
        if missing == 0:
            return
        self.dropped_frames += missing
        if missing <= self.max_gap_frames or self.on_gap == "ignore":
            return
        log.debug("gap of %d frames: %s", missing, self.on_gap)
        if self.on_gap == "reset":
            self._head, self._filled = -1, 0
            self.gap_resets += 1
        elif self._filled:
            self._hold(missing)

    # --- output ---------------------------------------------------------------------
    def update(self, frame_rgb: np.ndarray, timestamp_s: float) -> Reading | None:
        """Add one frame; return a :class:`Reading` once the window holds T frames.

        frame_rgb: (S, S, 3) uint8 RGB, S = the checkpoint's image size (after
            preprocessing). timestamp_s: capture time in seconds (any epoch,
            strictly increasing).
        """
        start = time.perf_counter()
        self._check_frame(frame_rgb)
        t = self._check_time(timestamp_s)
        self._handle_gap(self._missing_frames(t))
        self._push(frame_rgb, t)
        self._last_time = t
        self.frame_index += 1
        if not self.ready:
            return None
        window = self._frames[:, self._head + 1 : self._head + 1 + self.window]
        pressure = self.backend.run_incremental(window, min(self._unseen, self.window))[0]
        self._unseen = 0
        return self._reading(pressure, t, start)

    def add_frame(self, frame_rgb: np.ndarray, timestamp_s: float) -> None:
        """Buffer a frame without running the model; the next :meth:`update` covers it.

        For a live loop that fell behind the camera: add the frames it has not processed
        yet in order, then ``update`` with the newest, so the window stays T consecutive
        frames (the backend normalises each added frame once). Same checks as ``update``.
        """
        self._check_frame(frame_rgb)
        t = self._check_time(timestamp_s)
        self._handle_gap(self._missing_frames(t))
        self._push(frame_rgb, t)
        self._last_time = t
        self.frame_index += 1

    def _reduction_cache(self) -> None:
        g = self.geometry
        n, size = self.image_size, g.sensor_size_mm
        centres = (np.arange(n) + 0.5) / n
        self._coord_mm = (0.5 - centres) * size  # x of each column = y of each row, mm
        self._pixel_area_mm2 = g.mm_per_px**2
        self._kpa_to_n = g.pixel_area_m2 * 1000.0  # kPa * m^2 * (Pa/kPa) = N

    def _reading(self, pressure: np.ndarray, t: float, start: float) -> Reading:
        pressure = np.asarray(pressure, dtype=np.float32)  # backends hand over their output
        np.maximum(pressure, 0.0, out=pressure)
        pressure.flags.writeable = False
        total = float(pressure.sum(dtype=np.float64))
        force_n = total * self._kpa_to_n
        if total > 0:
            cop = np.array(
                [
                    pressure.sum(axis=0, dtype=np.float64) @ self._coord_mm / total,
                    pressure.sum(axis=1, dtype=np.float64) @ self._coord_mm / total,
                ]
            )
        else:
            cop = np.full(2, np.nan)
        cop.flags.writeable = False
        mask = self._contact_mask(pressure)
        mask.flags.writeable = False
        return Reading(
            pressure_kpa=pressure,
            force_n=force_n,
            cop_mm=cop,
            has_contact=bool(force_n >= self.contact_force_n),
            contact_mask=mask,
            contact_area_mm2=float(np.count_nonzero(mask)) * self._pixel_area_mm2,
            timestamp_s=t,
            latency_s=time.perf_counter() - start,
            frame_index=self.frame_index,
            dropped_frames=self.dropped_frames,
        )

    def _contact_mask(self, pressure: np.ndarray) -> np.ndarray:
        mask = pressure >= self.contact_threshold_kpa
        if self.contact_method == "otsu" and mask.any():
            mask &= pressure >= otsu_threshold(pressure[mask])
        return mask

    def predict_window(self, frames: np.ndarray) -> np.ndarray:
        """Run the backend on a full window: (T, S, S, 3) uint8 RGB -> (S, S) float32 kPa."""
        self.model.check_frames(frames, "frames")
        return np.array(self.backend.run(np.ascontiguousarray(frames)[None])[0])

    def close(self) -> None:
        self.backend.close()

    def __enter__(self) -> PressurePredictor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"PressurePredictor({self.model.source}, backend={self.backend.describe()}, "
            f"window={self.window}, fps={self.fps:g}, on_gap={self.on_gap!r})"
        )


def otsu_threshold(values: np.ndarray, bins: int = OTSU_BINS) -> float:
    """Otsu's threshold of a 1-D sample (maximises the between-class variance)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        return lo
    hist, edges = np.histogram(values, bins=bins, range=(lo, hi))
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean0 = m0 / w0
        mean1 = (m0[-1] - m0) / w1
        between = w0 * w1 * (mean0 - mean1) ** 2
    between = np.nan_to_num(between[:-1], nan=-1.0)
    return float(edges[int(np.argmax(between)) + 1])
