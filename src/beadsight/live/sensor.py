"""Live sensing: frames from a camera, a video file or the simulator -> pressure readings at
the camera rate, for robot code, the web viewer, the network stream and recorders.

::

    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    settings = LiveSettings(backend="auto")  # how it runs
    with LiveSensor("model.pt", source=0, settings=settings) as sensor:  # or "video.avi", "sim"
        for reading in sensor.readings():  # beadsight.inference.predictor.PressureReading
            print(reading.timestamp_s, reading.force_n, reading.cop_mm)

Threads. The source is a :class:`beadsight.devices.Camera` with its own reader thread
that keeps the frames with their capture timestamps (a consumer more than a window
behind skips frames; capture never waits for inference). :class:`LiveSensor` runs one
sensing thread: newest frame -> preprocessing ->
:class:`~beadsight.inference.predictor.PressurePredictor` -> listeners. Listeners (callbacks,
``readings()`` iterators, the viewer, the stream server, recorders) are called on the
sensing thread and must return quickly; the ones shipped here only copy a reference into
their own queue and do their work (encoding, sending, writing) on their own threads.

The rest reference of a rest-referenced model is taken from still frames at start-up (no
reading until then; a stored rest, ``LiveSettings.rest_file``, serves from the first frame)
and again whenever the pouch is unloaded and still (:mod:`beadsight.health.rest`).

Faults (timings in :mod:`~beadsight.live.settings`). A camera that disappears
(unplugged, driver error) puts the sensor in the ``no_signal`` state and is reopened with
exponential backoff (``RECONNECT_INITIAL_S`` doubling up to ``RECONNECT_MAX_S``); a video
file that ends finishes the stream (state ``ended``) unless ``loop=True``; a source that
stops delivering frames for ``NO_SIGNAL_AFTER_S`` is ``no_signal`` until frames return.
Frames whose size does not fit the model, and a checkpoint the chosen backend refuses, are
errors raised by :meth:`LiveSensor.start`, before any thread runs.

See also :mod:`~beadsight.live.settings`, :mod:`~beadsight.live.listeners` (what the
thread produces, who receives it), :mod:`~beadsight.live.stats`, :mod:`~beadsight.live.run`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.assets import shipped_model_path
from beadsight.checkpoint import PressureModel
from beadsight.data.rest import RestReference, load_rest_file
from beadsight.devices.base import (
    Camera,
    CameraDisconnectedError,
    CameraEndedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Frame,
)
from beadsight.errors import BeadSightError, ConfigError
from beadsight.health.monitor import HealthReport
from beadsight.health.watch import SensorWatch
from beadsight.inference.predictor import PressurePredictor, PressureReading
from beadsight.live.listeners import (
    READING_QUEUE_SIZE,
    CallbackListener,
    LiveListener,
    LiveStatus,
    LiveUpdate,
    UpdateQueue,
)
from beadsight.live.recording.recorder import RecordingSlot
from beadsight.live.settings import LiveSettings
from beadsight.live.sources import frame_converter, open_camera
from beadsight.live.stats import LiveStats, RateMeter

logger = logging.getLogger(__name__)

WAITING_FOR_REST = "waiting for the pouch to be unloaded and still to take the rest reference"

__all__ = ["LiveSensor"]


# --- the sensor ------------------------------------------------------------------------
class LiveSensor:
    """Camera/video/simulator -> pressure readings at the camera rate, on a background thread.

    checkpoint: a checkpoint path or a loaded PressureModel (default: the shipped sim
        model). source: camera index (int or digits) or device path, video file path,
        ``"sim"``, or a :class:`beadsight.devices.Camera` (not yet connected).
    settings: :class:`~beadsight.live.settings.LiveSettings`: the predictor's runtime
        (built by :meth:`PressurePredictor.from_checkpoint
        <beadsight.inference.predictor.PressurePredictor.from_checkpoint>`; one that
        cannot run this checkpoint is refused by :meth:`start`), preprocessing, the
        source's options, fault timing, ``max_readings`` (default: ``LiveSettings()``).

    Use as a context manager (``with LiveSensor(...) as sensor``) or call :meth:`start`
    / :meth:`stop`. :meth:`open` does everything :meth:`start` does except starting the
    sensing thread, so listeners and recordings added between the two see every reading.
    """

    def __init__(
        self,
        checkpoint: str | Path | PressureModel | None = None,
        source: int | str | Path | Camera = "sim",
        settings: LiveSettings | None = None,
    ):
        if settings is not None and not isinstance(settings, LiveSettings):
            raise TypeError(f"settings must be LiveSettings or None, got {type(settings).__name__}")
        settings = settings if settings is not None else LiveSettings()
        self.settings = settings
        self.max_readings = settings.max_readings
        self._checkpoint = checkpoint if checkpoint is not None else shipped_model_path()
        self._source_spec = source
        self._first_frame_timeout_s = settings.first_frame_timeout_s
        self._no_signal_after_s = settings.no_signal_after_s
        self._backoff_s = (settings.reconnect_initial_s, settings.reconnect_max_s)
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
        self._recording = RecordingSlot(self.add_listener, self.remove_listener)
        self._meter = RateMeter(stale_after_s=settings.no_signal_after_s)
        self._status = LiveStatus("starting", "not started", time.time())
        self._last_timestamp = -math.inf
        self.watch: SensorWatch | None = None

    # --- life cycle ----------------------------------------------------------------
    def open(self) -> LiveSensor:
        """Load the model, open the source and check its first frame (no thread yet).

        Raises if the backend refuses the checkpoint, the source cannot be opened or
        gives no frame, or its frames do not fit the model. Idempotent.
        """
        if self.model is not None:
            return self
        settings = self.settings
        self.predictor = PressurePredictor.from_checkpoint(
            self._checkpoint, **settings.predictor_arguments()
        )
        model = self.predictor.model
        try:
            rest_file, reference = settings.rest_file, None
            if rest_file:
                reference = load_rest_file(rest_file, model.image_size)
                logger.info("live: rest reference from %s (until the next one is taken)", rest_file)
            if reference is not None and model.rest:
                self.predictor.set_rest(reference.image)
            self.source = open_camera(
                self._source_spec,
                image_size=model.image_size,
                fps=settings.source_fps,
                loop=settings.loop,
                seed=settings.seed,
                any_size=settings.preprocess != "auto",
                drift=settings.sim_drift,
            )
            self.source.connect()
            first = self.source.read_latest(self._first_frame_timeout_s)
            self._convert = frame_converter(
                first, self.source.name, model.image_size, settings.preprocess
            )
            self._frame_hw = first.image.shape[:2]
        except BaseException:
            self._close_source_and_predictor()
            raise
        self.model, self._first = model, first
        if model.rest or settings.health:
            self.watch = SensorWatch(
                model.geometry.sensor_size_mm,
                reference=reference,
                health=settings.health,
                background=True,
                on_rest=self._new_rest,
            )
        logger.info("live: %s, source %s", self.predictor, self.source.name)
        return self

    @property
    def health(self) -> HealthReport | None:
        """The newest health report (None where health is not tracked)."""
        if self.watch is None or not self.settings.health:
            return None
        return self.watch.report

    def _new_rest(self, rest: RestReference) -> None:
        """A new rest reference (start-up, or the pouch unloaded and still again)."""
        if self.model is not None and self.model.rest:
            self.predictor.set_rest(rest.image)

    @property
    def rest(self) -> RestReference | None:
        """The rest reference in use (None before the first, or where none is kept)."""
        return self.watch.rest if self.watch is not None else None

    @property
    def rest_requested(self) -> bool:
        """:meth:`retake_rest` was called and its rest reference is not taken yet."""
        return self.watch is not None and self.watch.tracker.requested

    def retake_rest(self) -> None:
        """Take the next still frames as the rest reference, whatever the model reads: for a
        pouch known to be unloaded that reads a load (bumped or re-seated; docs/live.md).
        Any thread; ConfigError where no rest reference is kept."""
        self._require_started()
        if self.watch is None:
            raise ConfigError(
                f"checkpoint {self.model.source} has no rest input and health is off: "
                "there is no rest reference to take"
            )
        self.watch.request_rest()

    def start(self) -> LiveSensor:
        """:meth:`open` (if not done yet), then start the sensing thread."""
        if self._thread is not None:
            raise RuntimeError("LiveSensor already started")
        self.open()
        self._set_status("warming_up", f"filling the {self.model.span}-frame window")
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
            if self.watch is not None:
                self.watch.close()
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
        """Rate and latency of sensing, with the source's camera truth."""
        return self._meter.snapshot().with_camera(self.source)

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

    def on_reading(self, callback: Callable[[PressureReading], None]) -> Callable[[], None]:
        """Call ``callback(reading)`` on the sensing thread for every reading (keep it
        short: the next frame waits for it). Returns a function that unregisters it."""
        return self.add_listener(CallbackListener(callback, unwrap=True))

    def on_update(self, callback: Callable[[LiveUpdate], None]) -> Callable[[], None]:
        """Like :meth:`on_reading` with the :class:`LiveUpdate` (frame, latency, ...)."""
        return self.add_listener(CallbackListener(callback, unwrap=False))

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

    def readings(self, maxsize: int = READING_QUEUE_SIZE) -> Iterator[PressureReading]:
        """Iterate over :class:`~beadsight.inference.predictor.PressureReading` objects (see
        :meth:`updates`)."""
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
        return self._recording.start(path, model.geometry, self._provenance(), overwrite, on_error)

    def stop_recording(self) -> Path | None:
        """Finish the current recording; returns its path (None if not recording).

        Raises the error that stopped the recording (disk full, ...), if one did.
        """
        return self._recording.stop()

    @property
    def recording(self) -> tuple[Path, int] | None:
        """(path, readings written so far) of the current recording, or None."""
        return self._recording.current

    @property
    def recording_error(self) -> str | None:
        """Why the last recording stopped by itself (disk full, ...), until the next start."""
        return self._recording.error

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
            if self._stop.is_set() and self._status.state not in ("ended", "error"):
                self._set_status("stopped", "stopped")  # listeners hear it before finish()
            self._done.set()
            for listener in self._listeners:
                try:
                    listener.finish()
                except Exception:
                    logger.exception("live: a listener failed to finish")

    def _sense(self) -> None:
        source, window = self.source, self.model.span
        # indices start at 0: frames captured before the first one read count as skipped
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
                    batch, last_index = ([first] if first is not None else []), None
                    continue
                except DeviceTimeoutError:
                    self._set_status(
                        "no_signal",
                        f"no frame from {source.name} for {self._no_signal_after_s:g} s",
                    )
                    continue
            skipped = max(batch[0].index - last_index - 1, 0) if last_index is not None else 0
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
            rgb = self._convert(frame)
            self.predictor.add_frame(rgb, frame.timestamp_s)
            if self.watch is not None:
                self.watch.observe(rgb, frame.timestamp_s)

    def _process(self, frame: Frame) -> None:
        """Run the model on the window ending with ``frame``; publish the reading."""
        if not self._accept_time(frame):
            return
        rgb = self._convert(frame)
        reading = self.predictor.update(rgb, frame.timestamp_s)
        if reading is None:
            waiting = self.model.rest and self.predictor.rest is None
            filling = f"filling the {self.model.span}-frame window"
            self._set_status("warming_up", WAITING_FOR_REST if waiting else filling)
            if self.watch is not None:
                self.watch.observe(rgb, frame.timestamp_s)
            return
        report = self.watch.process(rgb, reading) if self.watch is not None else None
        health = report if self.settings.health else None
        latency = time.time() - frame.timestamp_s
        self._meter.add_reading(
            time.monotonic(), latency, reading.latency_s, reading.dropped_frames
        )
        self._set_status("ok", f"{self.source.name}")
        update = LiveUpdate(
            reading, rgb, latency, frame.reference_force_n, frame.source_index, health
        )
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
            if self.watch is not None:
                self.watch.reset()
            return first
