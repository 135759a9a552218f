"""Live sensing: frames from a camera, a video file or the simulator -> pressure readings at
the camera rate, for robot code, the web viewer, the network stream and recorders.

::

    from beadsight.live.sensor import LiveSensor

    with LiveSensor("model.pt", source=0) as sensor:  # camera 0; or "video.avi", or "sim"
        for reading in sensor.readings():  # beadsight.inference.predictor.Reading, newest first-come
            print(reading.timestamp_s, reading.force_n, reading.cop_mm)

Threads. The source is a :class:`beadsight.devices.Camera` with its own reader thread
that keeps the frames with their capture timestamps (a consumer more than a window
behind skips frames; capture never waits for inference). :class:`LiveSensor` runs one
sensing thread: newest frame -> preprocessing ->
:class:`~beadsight.inference.predictor.PressurePredictor` -> listeners. Listeners (callbacks,
``readings()`` iterators, the viewer, the stream server, recorders) are called on the
sensing thread and must return quickly; the ones shipped here only copy a reference into
their own queue and do their work (encoding, sending, writing) on their own threads.

Faults. A camera that disappears (unplugged, driver error) puts the sensor in the
``no_signal`` state and is reopened with exponential backoff
(:data:`RECONNECT_INITIAL_S` doubling up to :data:`RECONNECT_MAX_S`); a video file
that ends finishes the stream (state ``ended``) unless ``loop=True``; a source that
stops delivering frames for :data:`NO_SIGNAL_AFTER_S` is ``no_signal`` until frames
return. Frames whose size does not fit the model, and a checkpoint the chosen backend
refuses, are errors raised by :meth:`LiveSensor.start`, before any thread runs.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from beadsight.checkpoint import PressureModel, load_checkpoint, shipped_model_path
from beadsight.devices.base import (
    Camera,
    CameraDisconnectedError,
    CameraEndedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Frame,
)
from beadsight.errors import BeadSightError, ConfigError
from beadsight.inference.predictor import PressurePredictor, Reading
from beadsight.live.recorder import Recorder, open_recording_writer
from beadsight.live.sources import frame_converter, open_camera

logger = logging.getLogger(__name__)

FIRST_FRAME_TIMEOUT_S = 15.0  # a source that gives no frame this long after opening fails
NO_SIGNAL_AFTER_S = 1.0  # no new frame for this long -> state "no_signal"
RECONNECT_INITIAL_S = 0.5  # first wait before reopening a lost camera; doubles per try
RECONNECT_MAX_S = 8.0  # longest wait between reopening attempts
STATS_WINDOW_S = 5.0  # achieved rate and latency percentiles cover this recent span
READING_QUEUE_SIZE = 256  # readings() buffers this many before dropping the oldest

STATES = ("starting", "ok", "warming_up", "no_signal", "ended", "stopped", "error")


# --- what the sensing thread produces ------------------------------------------------
@dataclass(frozen=True)
class LiveUpdate:
    """One reading with the frame it came from (what the viewer and recorders get).

    reading: the predictor's :class:`~beadsight.inference.predictor.Reading` (its ``latency_s`` is
        the inference time only).
    frame_rgb: (S, S, 3) uint8 RGB model input (the newest frame of the window).
    latency_s: capture -> reading available, s (capture timestamp to the moment the
        reading left the predictor).
    reference_force_n: the true force if the source knows it (the simulator), else NaN.
    source_index: the frame's index in the source's stream.
    """

    reading: Reading
    frame_rgb: np.ndarray
    latency_s: float
    reference_force_n: float
    source_index: int


@dataclass(frozen=True)
class LiveStatus:
    """The sensor's state: one of :data:`STATES`, a human-readable message, and since when."""

    state: str
    message: str
    since_s: float  # time.time() of the change

    @property
    def has_signal(self) -> bool:
        return self.state in ("ok", "warming_up")


@dataclass(frozen=True)
class LiveStats:
    """Rates and latencies over the last :data:`STATS_WINDOW_S` (latencies in seconds).

    latency: capture -> reading available; inference: the predictor's own time.
    rate_hz: readings per second; source_rate_hz: frames per second from the source.
    When inference is slower than the camera, the frames that arrived meanwhile enter
    the window without a reading of their own (rate_hz < source_rate_hz) so the window
    stays consecutive; skipped_frames: frames that never entered the window (more than
    a window behind); dropped_frames: gaps the predictor saw in the capture timestamps
    (frames the camera itself lost, plus skipped ones).
    """

    readings: int
    frames: int  # frames taken from the source (each entered the window)
    rate_hz: float
    source_rate_hz: float
    latency_p50_s: float
    latency_p99_s: float
    inference_p50_s: float
    inference_p99_s: float
    skipped_frames: int
    dropped_frames: int

    def summary(self) -> str:
        def ms(v: float) -> str:
            return "-" if math.isnan(v) else f"{v * 1e3:.1f}"

        return (
            f"{self.rate_hz:.1f} Hz (source {self.source_rate_hz:.1f} Hz), latency p50 "
            f"{ms(self.latency_p50_s)} ms p99 {ms(self.latency_p99_s)} ms, inference p50 "
            f"{ms(self.inference_p50_s)} ms p99 {ms(self.inference_p99_s)} ms, "
            f"{self.readings} readings, skipped {self.skipped_frames}, "
            f"dropped {self.dropped_frames}"
        )


class _RateMeter:
    """Sliding-window rate and latency percentiles; thread-safe."""

    def __init__(self, window_s: float = STATS_WINDOW_S, stale_after_s: float = NO_SIGNAL_AFTER_S):
        self.window_s = window_s
        self.stale_after_s = stale_after_s  # no event for this long: the rate is 0
        self._lock = threading.Lock()
        self._readings: deque[tuple[float, float, float]] = deque()  # (done, latency, infer)
        self._frames: deque[float] = deque()  # arrival times of source frames
        self.count = 0
        self.frames = 0
        self.skipped = 0
        self.dropped = 0

    def _trim(self, now: float) -> None:
        while self._readings and self._readings[0][0] < now - self.window_s:
            self._readings.popleft()
        while self._frames and self._frames[0] < now - self.window_s:
            self._frames.popleft()

    def add_frames(self, now: float, count: int, skipped: int) -> None:
        with self._lock:
            self._frames.extend([now] * count)
            self.frames += count
            self.skipped += skipped
            self._trim(now)

    def add_reading(self, now: float, latency_s: float, inference_s: float, dropped: int) -> None:
        with self._lock:
            self._readings.append((now, latency_s, inference_s))
            self.count += 1
            self.dropped = dropped
            self._trim(now)

    def _rate(self, times: list[float], now: float) -> float:
        if len(times) < 2 or now - times[-1] > self.stale_after_s:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    def snapshot(self) -> LiveStats:
        now = time.monotonic()
        with self._lock:
            self._trim(now)
            rows = np.array(self._readings, dtype=np.float64).reshape(-1, 3)
            arrivals = list(self._frames)
            count, frames, skipped, dropped = self.count, self.frames, self.skipped, self.dropped
        if len(rows):
            lat = np.percentile(rows[:, 1], [50, 99])
            inf = np.percentile(rows[:, 2], [50, 99])
        else:
            lat = inf = (math.nan, math.nan)
        return LiveStats(
            readings=count,
            frames=frames,
            rate_hz=self._rate(list(rows[:, 0]), now),
            source_rate_hz=self._rate(arrivals, now),
            latency_p50_s=float(lat[0]),
            latency_p99_s=float(lat[1]),
            inference_p50_s=float(inf[0]),
            inference_p99_s=float(inf[1]),
            skipped_frames=skipped,
            dropped_frames=dropped,
        )


# --- listeners -------------------------------------------------------------------------
class LiveListener(Protocol):
    """Receives everything the sensing thread produces; every method must return quickly."""

    def push(self, update: LiveUpdate) -> None: ...

    def status(self, status: LiveStatus) -> None: ...

    def finish(self) -> None: ...


class _CallbackListener:
    def __init__(self, callback: Callable[[Any], None], unwrap: bool):
        self.callback, self.unwrap = callback, unwrap

    def push(self, update: LiveUpdate) -> None:
        self.callback(update.reading if self.unwrap else update)

    def status(self, status: LiveStatus) -> None:
        pass

    def finish(self) -> None:
        pass


class UpdateQueue:
    """A bounded queue of updates for one consumer; drops the oldest when full.

    ``get(timeout)`` returns the next update, or None on timeout; after :meth:`finish`
    and once empty it raises :class:`StopIteration`-free ``EOFError``.
    """

    def __init__(self, maxsize: int = READING_QUEUE_SIZE):
        self._items: deque[LiveUpdate] = deque(maxlen=maxsize)
        self._cond = threading.Condition()
        self._finished = False
        self.dropped = 0

    def push(self, update: LiveUpdate) -> None:
        with self._cond:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
                if self.dropped == 1 or self.dropped % 100 == 0:
                    logger.warning("a reading consumer is too slow: %d dropped", self.dropped)
            self._items.append(update)
            self._cond.notify()

    def status(self, status: LiveStatus) -> None:
        pass

    def finish(self) -> None:
        with self._cond:
            self._finished = True
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> LiveUpdate | None:
        with self._cond:
            self._cond.wait_for(lambda: self._items or self._finished, timeout)
            if self._items:
                return self._items.popleft()
            if self._finished:
                raise EOFError
            return None


# --- the sensor ------------------------------------------------------------------------
class LiveSensor:
    """Camera/video/simulator -> pressure readings at the camera rate, on a background thread.

    checkpoint: a checkpoint path or a loaded PressureModel (default: the shipped sim
        model). source: camera index (int or digits) or device path, video file path,
        ``"sim"``, or a :class:`beadsight.devices.Camera` (not yet connected).
    backend, precision: passed to :class:`~beadsight.inference.predictor.PressurePredictor` (a
        backend that cannot run this checkpoint is refused by :meth:`start`).
    preprocess: None (automatic: frames at the model's size are used as they are, raw
        1280x1024 camera frames go through the reference pipeline), or a
        :meth:`~beadsight.preprocess.Preprocessor.from_spec` spec ("reference",
        "reference-linear", "none", a fisheye calibration .json).
    fps: rate of the simulator (default 30) or the rate asked of a camera; a video file
        plays at its own rate. loop: restart a video at its end. seed: the
        simulator's seed. predictor_options: extra PressurePredictor keyword arguments.
    no_signal_after_s: no new frame for this long -> state ``no_signal``.
    reconnect_backoff_s: (first, longest) wait between attempts to reopen a lost camera;
        the wait doubles after each failed attempt.
    max_readings: end sensing (state ``ended``) after this many readings.

    Use as a context manager (``with LiveSensor(...) as sensor``) or call :meth:`start`
    / :meth:`stop`. :meth:`open` does everything :meth:`start` does except starting the
    sensing thread, so listeners and recordings added between the two see every reading.
    """

    def __init__(
        self,
        checkpoint: str | Path | PressureModel | None = None,
        source: int | str | Path | Camera = "sim",
        backend: Any = "auto",
        precision: str = "auto",
        *,
        preprocess: str | Path | None = None,
        fps: float | None = None,
        loop: bool = False,
        seed: int = 0,
        predictor_options: dict[str, Any] | None = None,
        first_frame_timeout_s: float = FIRST_FRAME_TIMEOUT_S,
        no_signal_after_s: float = NO_SIGNAL_AFTER_S,
        reconnect_backoff_s: tuple[float, float] = (RECONNECT_INITIAL_S, RECONNECT_MAX_S),
        max_readings: int | None = None,
    ):
        if max_readings is not None and max_readings < 1:
            raise ConfigError(f"max_readings must be >= 1, got {max_readings}")
        self.max_readings = max_readings
        self._checkpoint = checkpoint if checkpoint is not None else shipped_model_path()
        self._source_spec = source
        self._backend = backend
        self._precision = precision
        self._preprocess_spec = preprocess
        self._fps = fps
        self._loop = loop
        self._seed = seed
        self._predictor_options = predictor_options or {}
        self._first_frame_timeout_s = first_frame_timeout_s
        self._no_signal_after_s = no_signal_after_s
        self._backoff_s = reconnect_backoff_s
        self.model: PressureModel | None = None
        self.predictor: PressurePredictor | None = None
        self.source: Camera | None = None
        self._convert: Callable[[Frame], np.ndarray] | None = None
        self._frame_hw: tuple[int, int] | None = None
        self._listeners: tuple[LiveListener, ...] = ()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._first: Frame | None = None
        self._error: BaseException | None = None
        self._recorder: Recorder | None = None
        self._failed_recorder: Recorder | None = None  # stopped by an error not yet raised
        self._meter = _RateMeter(stale_after_s=no_signal_after_s)
        self._status = LiveStatus("starting", "not started", time.time())
        self._last_timestamp = -math.inf

    # --- life cycle ----------------------------------------------------------------
    def open(self) -> LiveSensor:
        """Load the model, open the source and check its first frame (no thread yet).

        Raises if the backend refuses the checkpoint, the source cannot be opened or
        gives no frame, or its frames do not fit the model. Idempotent.
        """
        if self.model is not None:
            return self
        model = (
            self._checkpoint
            if isinstance(self._checkpoint, PressureModel)
            else load_checkpoint(self._checkpoint)
        )
        self.predictor = PressurePredictor(
            model, self._backend, self._precision, **self._predictor_options
        )
        try:
            self.source = open_camera(
                self._source_spec,
                image_size=model.image_size,
                fps=self._fps,
                loop=self._loop,
                seed=self._seed,
                any_size=self._preprocess_spec is not None,
            )
            self.source.connect()
            first = self.source.read_latest(self._first_frame_timeout_s)
            self._convert = frame_converter(
                first, self.source.name, model.image_size, self._preprocess_spec
            )
            self._frame_hw = first.image.shape[:2]
        except BaseException:
            self._close_source_and_predictor()
            raise
        self.model, self._first = model, first
        logger.info("live: %s, source %s", self.predictor, self.source.name)
        return self

    def start(self) -> LiveSensor:
        """:meth:`open` (if not done yet), then start the sensing thread."""
        if self._thread is not None:
            raise RuntimeError("LiveSensor already started")
        self.open()
        self._set_status("warming_up", f"filling the {self.model.window}-frame window")
        self._thread = threading.Thread(target=self._run, name="beadsight-live", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop sensing, finish any recording, close the source. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        try:
            self.stop_recording()
        finally:
            self._close_source_and_predictor()
            if self._status.state not in ("ended", "error"):
                self._set_status("stopped", "stopped")

    def _close_source_and_predictor(self) -> None:
        if self.source is not None:
            self.source.close()
        if self.predictor is not None:
            self.predictor.close()

    def __enter__(self) -> LiveSensor:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until sensing ends (source ended, error, stop); True if it has ended."""
        if self._thread is None:
            raise RuntimeError("LiveSensor not started")
        return self._done.wait(timeout)

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._done.is_set()

    @property
    def error(self) -> BaseException | None:
        """The exception that ended sensing, if one did."""
        return self._error

    # --- information ---------------------------------------------------------------
    @property
    def geometry(self):
        return self._require_started().geometry

    @property
    def status(self) -> LiveStatus:
        return self._status

    def stats(self) -> LiveStats:
        return self._meter.snapshot()

    def _require_started(self) -> PressureModel:
        if self.model is None:
            raise RuntimeError("LiveSensor not started: use `with LiveSensor(...)` or .start()")
        return self.model

    # --- consumers -----------------------------------------------------------------
    def add_listener(self, listener: LiveListener) -> Callable[[], None]:
        """Register a listener (called on the sensing thread); returns a remover."""
        with self._lock:
            self._listeners = (*self._listeners, listener)
        listener.status(self._status)
        if self._done.is_set():
            listener.finish()
        return lambda: self.remove_listener(listener)

    def remove_listener(self, listener: LiveListener) -> None:
        with self._lock:
            self._listeners = tuple(x for x in self._listeners if x is not listener)

    def on_reading(self, callback: Callable[[Reading], None]) -> Callable[[], None]:
        """Call ``callback(reading)`` on the sensing thread for every reading (keep it
        short: the next frame waits for it). Returns a function that unregisters it."""
        return self.add_listener(_CallbackListener(callback, unwrap=True))

    def on_update(self, callback: Callable[[LiveUpdate], None]) -> Callable[[], None]:
        """Like :meth:`on_reading` with the :class:`LiveUpdate` (frame, latency, ...)."""
        return self.add_listener(_CallbackListener(callback, unwrap=False))

    def updates(self, maxsize: int = READING_QUEUE_SIZE) -> Iterator[LiveUpdate]:
        """Iterate over updates from now on, until sensing ends (then re-raise its error).

        The iterator is registered when this is called, so calling it between
        :meth:`open` and :meth:`start` sees every reading. A consumer slower than the
        camera loses the oldest updates beyond ``maxsize``.
        """
        queue = UpdateQueue(maxsize)
        return self._drain(queue, self.add_listener(queue))

    def _drain(self, queue: UpdateQueue, remove: Callable[[], None]) -> Iterator[LiveUpdate]:
        try:
            while True:
                try:
                    update = queue.get()
                except EOFError:
                    break
                if update is not None:
                    yield update
        finally:
            remove()
        if self._error is not None:
            raise self._error

    def readings(self, maxsize: int = READING_QUEUE_SIZE) -> Iterator[Reading]:
        """Iterate over :class:`~beadsight.inference.predictor.Reading` objects (see :meth:`updates`)."""
        return (update.reading for update in self.updates(maxsize))

    # --- recording -----------------------------------------------------------------
    def start_recording(
        self,
        path: str | Path,
        *,
        overwrite: bool = False,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> Path:
        """Record every reading to ``path`` (.h5 readings file or .mcap) until
        :meth:`stop_recording`. Returns the path.

        An existing file is refused unless ``overwrite``. A write failure (disk full) ends
        the recording, not sensing: ``on_error(error)`` is called on the recorder's thread,
        :attr:`recording_error` tells, and :meth:`stop_recording` raises the error.
        """
        model = self._require_started()
        with self._lock:
            if self._recorder is not None:
                raise BeadSightError(f"already recording to {self._recorder.path}")
            self._failed_recorder = None  # its error was reported (recording_error, on_error)
            writer = open_recording_writer(path, model.geometry, self._provenance(), overwrite)
            recorder = Recorder(writer, lambda e: self._recording_failed(recorder, e, on_error))
            self._recorder = recorder
        self.add_listener(recorder)
        logger.info("recording to %s", path)
        return Path(path)

    def _recording_failed(
        self, recorder: Recorder, error: BaseException, on_error: Callable | None
    ) -> None:
        self.remove_listener(recorder)
        with self._lock:
            if self._recorder is recorder:
                self._recorder, self._failed_recorder = None, recorder
        if on_error is not None:
            on_error(error)

    def stop_recording(self) -> Path | None:
        """Finish the current recording; returns its path (None if not recording).

        Raises the error that stopped the recording (disk full, ...), if one did.
        """
        with self._lock:
            recorder = self._recorder or self._failed_recorder
            self._failed_recorder = None
        if recorder is None:
            return None
        self.remove_listener(recorder)
        try:
            return recorder.close()  # `recording` reports it until the file is complete
        finally:
            with self._lock:
                if self._recorder is recorder:
                    self._recorder = None

    @property
    def recording(self) -> tuple[Path, int] | None:
        """(path, readings written so far) of the current recording, or None."""
        recorder = self._recorder
        return None if recorder is None else (recorder.path, recorder.count)

    @property
    def recording_error(self) -> str | None:
        """Why the last recording stopped by itself (disk full, ...), until the next start."""
        failed = self._failed_recorder
        return None if failed is None else str(failed.error)

    def _provenance(self) -> dict[str, Any]:
        return {
            "checkpoint": self.model.source if self.model else None,
            "source": self.source.name if self.source else None,
            "backend": self.predictor.backend.describe() if self.predictor else None,
        }

    # --- the sensing thread --------------------------------------------------------
    def _set_status(self, state: str, message: str) -> None:
        if state == self._status.state and message == self._status.message:
            return
        self._status = LiveStatus(state, message, time.time())
        log = logger.warning if state in ("no_signal", "error") else logger.info
        log("live: %s: %s", state, message)
        for listener in self._listeners:
            self._call(listener.status, self._status)

    def _call(self, method: Callable[[Any], None], arg: Any) -> None:
        try:
            method(arg)
        except Exception:
            logger.exception("live: a listener failed")

    def _run(self) -> None:
        try:
            self._sense()
        except BaseException as e:
            self._error = e
            self._set_status("error", str(e))
            logger.exception("live: sensing stopped by an error")
        finally:
            self._done.set()
            for listener in self._listeners:
                try:
                    listener.finish()
                except Exception:
                    logger.exception("live: a listener failed to finish")

    def _sense(self) -> None:
        source, window = self.source, self.model.window
        batch, last_index = [self._first], -1
        self._first = None
        while not self._stop.is_set():
            if not batch:
                try:
                    batch = source.async_read(self._no_signal_after_s, window)
                except CameraEndedError as e:
                    self._set_status("ended", str(e))
                    return
                except CameraDisconnectedError as e:
                    first = self._reconnect(e)
                    batch, last_index = ([first] if first is not None else []), -1
                    continue
                except DeviceTimeoutError:
                    self._set_status(
                        "no_signal",
                        f"no frame from {source.name} for {self._no_signal_after_s:g} s",
                    )
                    continue
            skipped = max(batch[0].index - last_index - 1, 0) if last_index >= 0 else 0
            self._meter.add_frames(time.monotonic(), len(batch), skipped)
            for frame in batch[:-1]:  # fell behind the camera: keep the window consecutive
                self._add(frame)
            last_index = batch[-1].index
            self._process(batch[-1])
            batch = []
            if self.max_readings is not None and self._meter.count >= self.max_readings:
                self._set_status("ended", f"stopped after {self.max_readings} readings")
                return

    def _accept_time(self, frame: Frame) -> bool:
        if frame.timestamp_s <= self._last_timestamp:
            logger.warning("live: frame %d has a non-increasing timestamp; skipped", frame.index)
            return False
        self._last_timestamp = frame.timestamp_s
        return True

    def _add(self, frame: Frame) -> None:
        """Buffer a frame in the predictor's window without running the model."""
        if self._accept_time(frame):
            self.predictor.add_frame(self._convert(frame), frame.timestamp_s)

    def _process(self, frame: Frame) -> None:
        """Run the model on the window ending with ``frame``; publish the reading."""
        if not self._accept_time(frame):
            return
        rgb = self._convert(frame)
        reading = self.predictor.update(rgb, frame.timestamp_s)
        if reading is None:
            self._set_status("warming_up", f"filling the {self.model.window}-frame window")
            return
        latency = time.time() - frame.timestamp_s
        self._meter.add_reading(
            time.monotonic(), latency, reading.latency_s, reading.dropped_frames
        )
        self._set_status("ok", f"{self.source.name}")
        update = LiveUpdate(reading, rgb, latency, frame.reference_force_n, frame.index)
        for listener in self._listeners:
            self._call(listener.push, update)

    def _reconnect(self, error: BaseException) -> Frame | None:
        """Reconnect a lost camera with exponential backoff; None if stopped meanwhile."""
        delay, longest = self._backoff_s
        attempt = 0
        while True:
            attempt += 1
            reason = getattr(error, "detail", error)  # without the camera's name again
            self._set_status(
                "no_signal",
                f"{self.source.name}: {reason}; reopening in {delay:.1f} s (attempt {attempt})",
            )
            if self._stop.wait(delay):
                return None
            try:
                self.source.close()
                self.source.connect()
                first = self.source.read_latest(self._first_frame_timeout_s)
            except (DeviceNotConnectedError, DeviceTimeoutError) as e:
                error, delay = e, min(2 * delay, longest)
                continue
            if first.image.shape[:2] != self._frame_hw:
                raise BeadSightError(
                    f"source {self.source.name} came back with "
                    f"{first.image.shape[1]}x{first.image.shape[0]} frames, was "
                    f"{self._frame_hw[1]}x{self._frame_hw[0]}"
                )
            logger.info("live: %s reopened after %d attempt(s)", self.source.name, attempt)
            self.predictor.reset()
            return first


# --- running from the command line ------------------------------------------------------
class _Wake:
    """A listener that wakes :func:`run_live` when sensing ends."""

    def __init__(self, event: threading.Event):
        self.event = event

    def push(self, update: LiveUpdate) -> None:
        pass

    def status(self, status: LiveStatus) -> None:
        pass

    def finish(self) -> None:
        self.event.set()


def run_live(
    sensor: LiveSensor,
    *,
    viewer: bool = True,
    host: str = "127.0.0.1",
    port: int = 8000,
    viewer_options: dict[str, Any] | None = None,
    stream_port: int | None = None,
    stream_options: dict[str, Any] | None = None,
    output: str | Path | None = None,
    overwrite: bool = False,
    duration_s: float | None = None,
    report_every_s: float = 5.0,
    echo: Callable[[str], None] = print,
) -> LiveStats:
    """Run ``sensor`` with the viewer / stream / recording asked for, reporting stats every
    ``report_every_s``, until sensing ends (source end, ``max_readings``), ``duration_s``
    or Ctrl-C. With the viewer on, the end of sensing leaves the page up (showing "no
    signal") until Ctrl-C or ``duration_s``. The recording and the stream get every
    reading from the first. An existing ``output`` is refused unless ``overwrite``; a
    recording that fails (disk full) ends the run. Returns the final stats; re-raises the
    error that stopped sensing or the recording, if any.

    viewer_options: keyword arguments of :class:`~beadsight.live.viewer.server.ViewerServer`
    (max_fps, max_kpa, history_s, record_dir). stream_options: keyword arguments of
    :class:`~beadsight.live.stream.StreamServer` (max_age_s).
    """
    wake, servers, failed = threading.Event(), [], threading.Event()

    def recording_failed(error: BaseException) -> None:
        failed.set()
        wake.set()

    sensor.open()
    try:
        sensor.add_listener(_Wake(wake))
        if output is not None:
            path = sensor.start_recording(output, overwrite=overwrite, on_error=recording_failed)
            echo(f"recording to {path}")
        if stream_port is not None:
            from beadsight.live.stream import StreamServer

            servers.append(
                StreamServer(sensor.geometry, host, stream_port, **(stream_options or {}))
            )
            sensor.add_listener(servers[-1])
            echo(f"stream: tcp://{servers[-1].host}:{servers[-1].port} (see docs/live.md)")
        if viewer:
            from beadsight.live.viewer.server import ViewerServer

            servers.append(ViewerServer(sensor, host, port, **(viewer_options or {})))
            echo(f"viewer: {servers[-1].url}")
        sensor.start()
        _wait(sensor, wake, viewer, duration_s, report_every_s, echo, failed)
    except KeyboardInterrupt:
        echo("interrupted: stopping")
    finally:
        _finish(sensor, servers, echo)
    stats = sensor.stats()
    echo(f"final: {stats.summary()}")
    if sensor.error is not None:
        raise sensor.error
    return stats


def _finish(sensor: LiveSensor, servers: list[Any], echo: Callable[[str], None]) -> None:
    """Close the servers, finish the recording (raising its error), stop the sensor; safe to
    call twice."""
    try:
        while servers:
            servers.pop().close()
        recorded = sensor.stop_recording()
        if recorded is not None:
            echo(f"wrote {recorded}")
    finally:
        sensor.stop()


def _wait(sensor, wake, viewer, duration_s, report_every_s, echo, failed) -> None:
    now = time.monotonic()
    deadline = math.inf if duration_s is None else now + duration_s
    next_report = now + report_every_s
    ended = False
    while now < deadline:
        wake.wait(min(next_report, deadline) - now)
        now = time.monotonic()
        if failed.is_set():  # the recording failed: its error ends the run
            return
        if wake.is_set() and not ended:  # sensing ended
            if not viewer or sensor.error is not None:
                return
            ended = True
            echo(
                f"{sensor.status.state}: {sensor.status.message}; the viewer stays up "
                "(Ctrl-C to quit)"
            )
        if ended:
            wake.clear()
        if now >= next_report:
            next_report += report_every_s * max(1, math.ceil((now - next_report) / report_every_s))
            echo(f"{sensor.status.state}: {sensor.stats().summary()}")
