"""Streaming inference: one camera frame in, one pressure reading out.

:class:`PressurePredictor` owns a ring buffer of the last ``span`` frames (the frames
one input window covers: 15 for the reference model, 57 for the shipped one, which
sees every 4th of them) with their capture timestamps, runs the model through a
:mod:`beadsight.inference.runtimes` backend once the window is full, and turns the kPa
map into a :class:`PressureReading` (total force, centre of pressure, contact mask
and area; the reductions of :mod:`beadsight.geometry`).

Like segment-anything's ``SamPredictor``, the predictor itself does no file work: it
takes a loaded model and a built runtime. :meth:`PressurePredictor.from_checkpoint`
loads a checkpoint and chooses, probes and times the runtime::

    from beadsight import PressurePredictor

    predictor = PressurePredictor.from_checkpoint("best.pt")  # fastest accurate backend
    for frame_rgb, t in camera:  # (256, 256, 3) uint8 RGB, capture time in s
        reading = predictor.update(frame_rgb, t)
        if reading is not None:
            print(reading.force_n, reading.cop_mm)

Ring buffer
-----------
Frames are copied into a preallocated uint8 array of ``2 span`` slots: each frame is
written twice, at slots ``i`` and ``i + span``, so the window is always one
contiguous, oldest-first view ``buffer[i + 1 : i + 1 + span]`` that goes to the
backend without any per-frame allocation or reordering.

Dropped frames
--------------
The frame period is ``1 / fps`` with ``fps`` from the checkpoint's provenance
(``provenance["fps"]``, or the training dataset's fps recorded there), else
``PredictorSettings.fps``, else 30 (the reference camera). For each new frame the
number of frames missing before it is ``round(dt * fps) - 1`` where ``dt`` is the
time since the previous frame (a gap under ``GAP_TOLERANCE`` periods counts as none:
camera jitter is not a drop).

* Gaps of up to ``max_gap_frames`` missing frames are counted in
  ``PressureReading.dropped_frames`` and the window simply continues.
* Larger gaps are handled by ``on_gap``: ``"reset"`` (default) clears the buffer,
  which fills again from this frame (``update`` returns ``None`` for the next
  ``span - 1`` frames: the model never sees a window that spans a long hole);
  ``"hold"`` fills the missing frames with copies of the last frame received
  (zero-order hold, at most ``span - 1``), so readings continue at once;
  ``"ignore"`` counts the drop and continues.

Timestamps must increase strictly; a repeated or earlier timestamp is refused
with a ValueError (feeding the same frame twice is a capture bug).

Rest reference
--------------
A rest-referenced model (``model.rest == 1``) reads pressure against an image of the
unloaded pouch, the *rest image*. :meth:`PressurePredictor.set_rest` sets it (one
(S, S, 3) image, or (K, S, S, 3) frames averaged by
:func:`beadsight.data.rest.average_rest`, the one averaging rule); :attr:`~PressurePredictor.rest`
reads it back. Until one is set, ``PredictorSettings.initial_rest`` decides:
``"first_frames"`` (default) averages the first :data:`~beadsight.data.rest.REST_FRAMES`
frames the predictor receives into the rest image (logged once: keep the pouch unloaded
when sensing starts); ``"wait"`` buffers frames but returns no reading until
:meth:`~PressurePredictor.set_rest` is called (``beadsight live`` waits for still frames,
or uses a stored rest). The rest image survives :meth:`~PressurePredictor.reset` (it
belongs to the pouch, not to the stream). Models without a rest input ignore all this.

Contact
-------
``contact_mask`` is ``pressure_kpa >= contact_threshold_kpa``: by default the pressure
of the release force of :class:`~beadsight.config.ContactThresholds` (10 g) spread
over the finger's disk, about 0.8 kPa. ``contact_method="otsu"`` keeps, of those
pixels, Otsu's foreground (:func:`beadsight.geometry.otsu_masks`, the
evaluation's IoU definition). ``has_contact`` is ``force_n >= contact_force_n``
(default: the 50 g contact force).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.config import ContactThresholds, SensorGeometry
from beadsight.data.rest import REST_FRAMES, average_rest
from beadsight.files import Closes
from beadsight.geometry import (
    centre_of_pressure_mm,
    contact_area_mm2,
    disk_pressure_kpa,
    otsu_masks,
    total_force_n,
)
from beadsight.inference.runtimes import Backend, TorchBackend
from beadsight.inference.select import create_backend

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0  # the reference camera's frame rate, used when the checkpoint names none
DEFAULT_MAX_GAP_FRAMES = 3  # missing frames tolerated before on_gap applies (100 ms at 30 fps)
GAP_TOLERANCE = 1.5  # dt below this many frame periods is jitter, not a dropped frame
GAP_POLICIES = ("reset", "hold", "ignore")
CONTACT_METHODS = ("threshold", "otsu")
INITIAL_REST = ("first_frames", "wait")


@dataclass(frozen=True)
class PressureReading:
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


@dataclass(frozen=True)
class PredictorSettings:
    """How a :class:`PressurePredictor` treats time and contact (module docstring)."""

    fps: float | None = None  # frame rate for gap detection when the checkpoint names none
    max_gap_frames: int = DEFAULT_MAX_GAP_FRAMES  # missing frames tolerated before on_gap
    on_gap: str = "reset"  # reset | hold | ignore
    contact_threshold_kpa: float | None = None  # None: the release force over the finger
    contact_method: str = "threshold"  # threshold | otsu
    contact_force_n: float | None = None  # has_contact at or above; None: the 50 g force
    initial_rest: str = (
        "first_frames"  # rest-referenced models before set_rest: first_frames | wait
    )

    def __post_init__(self) -> None:
        if self.initial_rest not in INITIAL_REST:
            raise ValueError(
                f"initial_rest must be one of {INITIAL_REST}, got {self.initial_rest!r}"
            )
        if self.on_gap not in GAP_POLICIES:
            raise ValueError(f"on_gap must be one of {GAP_POLICIES}, got {self.on_gap!r}")
        if self.contact_method not in CONTACT_METHODS:
            raise ValueError(
                f"contact_method must be one of {CONTACT_METHODS}, got {self.contact_method!r}"
            )
        gap = self.max_gap_frames
        if isinstance(gap, bool) or int(gap) != gap or gap < 0:
            raise ValueError(f"max_gap_frames must be an integer >= 0, got {gap}")
        object.__setattr__(self, "max_gap_frames", int(gap))
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be > 0, got {self.fps}")


def checkpoint_fps(model: PressureModel) -> float | None:
    """The camera rate the checkpoint's training data was recorded at, if it says."""
    meta = model.meta
    for source in (meta.provenance, meta.training):
        dataset = source.get("dataset")
        for value in (
            source.get("fps"),
            dataset.get("fps") if isinstance(dataset, dict) else None,
            source.get("dataset_fps"),
        ):
            try:
                fps = float(value) if value is not None else None
            except (TypeError, ValueError):
                fps = None
            if fps is not None and math.isfinite(fps) and fps > 0:
                return fps
    return None


class PressurePredictor(Closes):
    """Stateful frame-by-frame pressure estimation.

    model: a loaded :class:`~beadsight.checkpoint.PressureModel`.
    backend: a built :class:`~beadsight.inference.runtimes.Backend` for ``model``
        (default: eager torch in fp32 on the model's device).
    settings: :class:`PredictorSettings` (default: ``PredictorSettings()``).

    To load a checkpoint and choose the fastest backend that agrees with torch, use
    :meth:`from_checkpoint`. Not thread-safe: call :meth:`update` from one thread.
    """

    def __init__(
        self,
        model: PressureModel,
        backend: Backend | None = None,
        *,
        settings: PredictorSettings | None = None,
    ):
        if not isinstance(model, PressureModel):
            raise TypeError(
                f"PressurePredictor takes a loaded PressureModel, got {type(model).__name__}; "
                "to load a checkpoint file use PressurePredictor.from_checkpoint(path, ...)"
            )
        if backend is not None and not isinstance(backend, Backend):
            raise TypeError(
                f"backend must be a built Backend or None, got {type(backend).__name__}; "
                "to choose a runtime by name use PressurePredictor.from_checkpoint(model, name)"
            )
        settings = settings if settings is not None else PredictorSettings()
        self.model = model
        self.backend = backend if backend is not None else TorchBackend(model, device=model.device)
        self.settings = settings
        self.geometry: SensorGeometry = model.geometry
        self.frames, self.span, self.image_size = model.frames, model.span, model.image_size
        self.fps = float(checkpoint_fps(model) or settings.fps or DEFAULT_FPS)
        self.max_gap_frames, self.on_gap = settings.max_gap_frames, settings.on_gap
        self.contact_method = settings.contact_method
        thresholds = ContactThresholds()
        release_kpa = disk_pressure_kpa(thresholds.release_n, self.geometry)
        self.contact_threshold_kpa = float(_default(settings.contact_threshold_kpa, release_kpa))
        self.contact_force_n = float(_default(settings.contact_force_n, thresholds.contact_n))
        s, n = self.image_size, self.span
        self._frames = np.zeros((1, 2 * n, s, s, 3), dtype=np.uint8)  # doubled ring buffer
        self._times = np.zeros(2 * n, dtype=np.float64)
        self._rest: np.ndarray | None = None  # the rest image, read-only (rest models)
        self._first: list[np.ndarray] = []  # first frames, averaged into the rest image
        self.reset()

    @classmethod
    def from_checkpoint(
        cls,
        checkpoint: PressureModel | str | Path,
        backend: str = "auto",
        precision: str = "auto",
        device: str | None = None,
        *,
        exported_model: str | Path | None = None,
        cache_dir: str | Path | None = "default",
        threads: int | None = None,
        settings: PredictorSettings | None = None,
    ) -> PressurePredictor:
        """Load ``checkpoint`` (a path, or an already loaded model) and build its backend.

        backend: "auto" (the fastest available backend that agrees with fp32 torch, see
        :func:`beadsight.inference.select.select_backend`), "torch", "onnx",
        "openvino" or "cuda"; precision: "fp32", "bf16" or "auto"; device: for the
        torch/cuda backends. exported_model: an exported ``.onnx`` / OpenVINO
        ``.xml`` file to run, refused unless it was exported from this checkpoint.
        cache_dir, threads: see :func:`beadsight.inference.select.create_backend`.
        settings: as for the constructor.
        """
        model = checkpoint if isinstance(checkpoint, PressureModel) else load_checkpoint(checkpoint)
        runtime = create_backend(
            model, backend, precision, device, exported_model, cache_dir, threads
        )
        return cls(model, runtime, settings=settings)

    # --- the rest image ---------------------------------------------------------------
    @property
    def rest(self) -> np.ndarray | None:
        """The rest image in use, (S, S, 3) uint8 RGB (read-only); None before one is set
        and for models without a rest input."""
        return self._rest

    def set_rest(self, image_or_frames: np.ndarray) -> np.ndarray:
        """Set the rest image of a rest-referenced model: ``image_or_frames`` is one
        (S, S, 3) uint8 RGB image of the unloaded pouch, or (K, S, S, 3) frames of it
        averaged with :func:`~beadsight.data.rest.average_rest`. Returns the rest image
        now in use (a read-only copy; the next reading uses it)."""
        if not self.model.rest:
            raise ValueError(
                f"set_rest: checkpoint {self.model.source} is not rest-referenced (it has no "
                "rest input)"
            )
        s = self.image_size
        array = np.asarray(image_or_frames)
        if array.ndim == 4 and array.shape[1:] == (s, s, 3) and array.dtype == np.uint8:
            image = average_rest(array)
        elif array.shape == (s, s, 3) and array.dtype == np.uint8:
            image = array.copy()
        else:
            raise ValueError(
                f"set_rest: expected a ({s}, {s}, 3) uint8 RGB image or (K, {s}, {s}, 3) "
                f"uint8 RGB frames, got {array.shape} {array.dtype}"
            )
        image.flags.writeable = False
        self._rest = image
        self._first = []
        return image

    def _collect_rest(self, frame_rgb: np.ndarray) -> None:
        """``initial_rest="first_frames"``: the first REST_FRAMES frames become the rest."""
        self._first.append(frame_rgb.copy())
        if len(self._first) >= REST_FRAMES:
            self.set_rest(np.stack(self._first))
            log.info(
                "rest image: the first %d frames received (keep the pouch unloaded when "
                "sensing starts, or call set_rest with frames of the unloaded pouch)",
                REST_FRAMES,
            )

    # --- state ----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all buffered frames and counters; the next span-1 updates return None.
        The rest image is kept (it belongs to the pouch, not to the stream)."""
        self._head = -1  # slot of the newest frame in [0, span)
        self._filled = 0  # valid frames in the window
        self._unseen = 0  # frames pushed since the backend last ran
        self._last_time: float | None = None
        self.frame_index = -1
        self.dropped_frames = 0
        self.gap_resets = 0

    @property
    def ready(self) -> bool:
        """True when the window holds span frames and, for a rest-referenced model, a rest
        image is set (the next update returns a reading)."""
        return self._filled >= self.span and (self._rest is not None or not self.model.rest)

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.fps

    def window_frames(self) -> np.ndarray:
        """The buffered window, (span, S, S, 3) uint8 RGB, oldest first (a read-only view).

        Only the newest ``min(filled, span)`` frames are meaningful before it is full.
        """
        start = self._head + 1
        view = self._frames[0, start : start + self.span].view()
        view.flags.writeable = False
        return view

    def window_timestamps(self) -> np.ndarray:
        """(span,) float64 capture times of the window's frames, oldest first."""
        start = self._head + 1
        return self._times[start : start + self.span].copy()

    # --- input ----------------------------------------------------------------------
    def _check_frame(self, frame_rgb: np.ndarray) -> None:
        s = self.image_size
        shape = getattr(frame_rgb, "shape", None)
        if shape is None or len(shape) != 3 or shape[-1] != 3:
            raise ValueError(
                f"frame_rgb: expected a ({s}, {s}, 3) uint8 RGB frame for checkpoint "
                f"{self.model.source}, got shape {shape}"
            )
        if shape[:2] != (s, s):
            raise ValueError(
                f"frame_rgb: the source delivers {shape[1]}x{shape[0]} px frames but the "
                f"checkpoint {self.model.source} expects {s}x{s} px (its preprocessing output "
                f"size); preprocess the camera frames to {s}x{s}"
            )
        if frame_rgb.dtype != np.uint8:
            raise ValueError(
                f"frame_rgb: expected dtype uint8 (0..255) {s}x{s}x3 RGB, got {frame_rgb.dtype}"
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
        head = (self._head + 1) % self.span
        self._frames[0, head] = frame_rgb
        self._frames[0, head + self.span] = frame_rgb
        self._times[head] = self._times[head + self.span] = t
        self._head = head
        self._filled = min(self._filled + 1, self.span)
        self._unseen += 1

    def _hold(self, copies: int) -> None:
        """Repeat the newest buffered frame ``copies`` times (zero-order hold)."""
        last = self._frames[0, self._head].copy()
        dt = self.frame_period_s
        t0 = self._last_time if self._last_time is not None else 0.0
        for k in range(min(copies, self.span - 1)):
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

    def add_frame(self, frame_rgb: np.ndarray, timestamp_s: float) -> None:
        """Buffer a frame without running the model; the next :meth:`update` covers it.

        For a live loop that fell behind the camera: add the frames it has not processed
        yet in order, then ``update`` with the newest, so the window stays consecutive
        (the backend normalises each added frame once). Same checks as ``update``.
        """
        self._check_frame(frame_rgb)
        t = self._check_time(timestamp_s)
        self._handle_gap(self._missing_frames(t))
        self._push(frame_rgb, t)
        self._last_time = t
        self.frame_index += 1
        if self.model.rest and self._rest is None and self.settings.initial_rest == "first_frames":
            self._collect_rest(frame_rgb)

    # --- output ---------------------------------------------------------------------
    def update(self, frame_rgb: np.ndarray, timestamp_s: float) -> PressureReading | None:
        """Add one frame; return a :class:`PressureReading` once the window is full.

        frame_rgb: (S, S, 3) uint8 RGB, S = the checkpoint's image size (after
            preprocessing). timestamp_s: capture time in seconds (any epoch,
            strictly increasing).
        """
        start = time.perf_counter()
        self.add_frame(frame_rgb, timestamp_s)
        if not self.ready:
            return None
        window = self._frames[:, self._head + 1 : self._head + 1 + self.span]
        pressure = self.backend.run_incremental(window, min(self._unseen, self.span), self._rest)[0]
        self._unseen = 0
        return self._reading(pressure, self._last_time, start)

    def _reading(self, pressure: np.ndarray, t: float, start: float) -> PressureReading:
        pressure = np.asarray(pressure, dtype=np.float32)  # backends hand over their output
        np.maximum(pressure, 0.0, out=pressure)
        pressure.flags.writeable = False
        exact = pressure.astype(np.float64)
        force_n = float(total_force_n(exact, self.geometry))
        cop = centre_of_pressure_mm(exact, self.geometry)
        cop.flags.writeable = False
        mask = self._contact_mask(pressure)
        mask.flags.writeable = False
        return PressureReading(
            pressure_kpa=pressure,
            force_n=force_n,
            cop_mm=cop,
            has_contact=bool(force_n >= self.contact_force_n),
            contact_mask=mask,
            contact_area_mm2=float(contact_area_mm2(mask, self.geometry)),
            timestamp_s=t,
            latency_s=time.perf_counter() - start,
            frame_index=self.frame_index,
            dropped_frames=self.dropped_frames,
        )

    def _contact_mask(self, pressure: np.ndarray) -> np.ndarray:
        mask = pressure >= self.contact_threshold_kpa
        if self.contact_method == "otsu" and mask.any():
            mask[mask] = otsu_masks(pressure[mask][None])[0]
        return mask

    def close(self) -> None:
        self.backend.close()

    def __repr__(self) -> str:
        return (
            f"PressurePredictor({self.model.source}, backend={self.backend.describe()}, "
            f"frames={self.frames}, span={self.span}, fps={self.fps:g}, on_gap={self.on_gap!r}"
            + (
                f", rest {'set' if self._rest is not None else 'not set'})"
                if self.model.rest
                else ")"
            )
        )


def _default(value: float | None, default: float) -> float:
    return default if value is None else value
