"""The camera base: a background reader, an ordered queue, the newest frame, frame accounting.

Every camera (:class:`~beadsight.devices.opencv.OpenCVCamera`,
:class:`~beadsight.devices.virtual.VirtualCamera` and its players) is a
:class:`BufferedCamera`: one reader thread per camera captures frames; each gets its
capture timestamps (monotonic and wall clock, taken as the capture returns; the wall
clock one made strictly increasing) and a capture index, and goes into a bounded queue
(for :meth:`~BufferedCamera.read` and :meth:`~BufferedCamera.async_read`) and into the
"latest" slot (for :meth:`~BufferedCamera.read_latest`). No read hands out a frame twice.

Pacing is an option of the camera, not a kind of camera: with ``realtime`` a video file
or played frames come at the camera's fps on its clock (host time, or a virtual rig's
simulated time), like a live camera; a camera that falls behind runs slower rather than
bursting to catch up. Without it they come as fast as the consumer takes them.

Frame accounting (:attr:`BufferedCamera.stats`):

* ``dropped``: frames the *device* lost, from timestamp gaps: a gap ``dt > 1.5 / fps``
  between consecutive captures counts ``max(1, round(dt * fps) - 1)`` frames (live
  cameras only; a file cannot lose frames).
* ``overflowed``: frames pushed out of the full queue because the reads fell behind
  (live cameras; files wait for the reader instead).
* ``skipped``: frames ``read_latest`` / ``async_read`` passed over on purpose to return
  the newest.
* ``duplicated``, ``delivered_fps``, ``requested_fps``, ``slow``: camera truth
  (:mod:`beadsight.devices.truth`): frames identical to the one before, and the rate the
  camera really delivers against the one asked (a warning below 90 %).

When capture fails (end of file, camera unplugged) the reader stops; reads return the
frames still queued, then raise :class:`CameraEndedError` (the normal end of a finite
camera) or :class:`CameraDisconnectedError` (a live camera was lost). A reconnect
starts a fresh stream whose indices continue from the last.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from beadsight.devices.base import (
    CameraConfigError,
    CameraDisconnectedError,
    CameraEndedError,
    DeviceContext,
    DeviceNotConnectedError,
    Frame,
    wait_or_time_out,
)
from beadsight.devices.clock import SimClock
from beadsight.devices.reader import ReaderThread
from beadsight.devices.truth import FrameTruth

logger = logging.getLogger(__name__)

DEFAULT_WIDTH_PX = 1280  # the reference sensor camera, MJPG
DEFAULT_HEIGHT_PX = 1024
DEFAULT_FPS = 30.0
DEFAULT_QUEUE_FRAMES = 64  # ~2 s at 30 fps; read() must keep up on average
GAP_FACTOR = 1.5  # a capture gap above this many frame periods means frames were lost
GAP_REPORT_S = 10.0  # after the first, capture gaps are logged as one summary line this often
MIN_READ_TIMEOUT_S = 2.0  # default read timeout: max(this, 10 frame periods)
MIN_TIMESTAMP_STEP_S = 1e-6  # consecutive t_unix stamps differ by at least this
QUEUE_FULL_POLL_S = 0.1  # a file reader waiting on a full queue checks for close this often

# what a capture hook returns: (image, reference_force_n), or with the frame's row in the
# file the camera plays: (image, reference_force_n, file_index)
Captured = tuple[np.ndarray, float] | tuple[np.ndarray, float, int]


@dataclass(frozen=True)
class CameraStats:
    """Frame counters since the camera object was made (see the module docstring)."""

    captured: int
    delivered: int
    dropped: int
    overflowed: int
    skipped: int
    duplicated: int = 0  # frames identical to the one before (devices.truth)
    delivered_fps: float = float("nan")  # capture rate over the last 2 s (host time)
    requested_fps: float = float("nan")  # the rate asked of the camera
    slow: bool = False  # delivered_fps below 90 % of requested_fps


def verify_mode(
    name: str, requested: tuple[int | None, int | None], actual: tuple[int, int], hint: str
) -> None:
    """Raise CameraConfigError naming the camera and both resolutions if they differ.

    requested: (width, height) px, None = accept any; actual: what the device delivers.
    """
    req_w, req_h = requested
    if (req_w is not None and req_w != actual[0]) or (req_h is not None and req_h != actual[1]):
        want = f"{req_w or '*'}x{req_h or '*'}"
        raise CameraConfigError(
            name, f"delivers {actual[0]}x{actual[1]} frames but {want} was requested", hint
        )


def check_image(name: str, image: object) -> np.ndarray:
    """``image`` as an (H, W, 3) uint8 array, or ValueError naming the camera and what came."""
    array = np.asarray(image)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name}: frames must be (H, W, 3) uint8, got {array.dtype} {array.shape}")
    return array


class Pacer:
    """Releases one frame per period of ``fps`` on ``clock`` (host or simulated time).

    A frame more than one period late re-anchors the schedule (the camera runs slower
    instead of bursting); ``delay_s`` postpones the schedule (a stalled camera).
    """

    def __init__(self, fps: float, clock: SimClock):
        self.period_s = 1.0 / fps
        self.clock = clock
        self._next_t: float | None = None

    def wait(self, stop: threading.Event, delay_s: float = 0.0) -> bool:
        """Wait for the next frame's time; False if ``stop`` was set first."""
        now = self.clock.now()
        if self._next_t is None:
            self._next_t = now
        self._next_t = max(self._next_t, now - self.period_s) + delay_s
        if not self.clock.wait_until(self._next_t, stop):
            return False
        self._next_t += self.period_s
        return True


class BufferedCamera(DeviceContext):
    """Base class of every camera: see the module docstring and :class:`~beadsight.devices.Camera`.

    Subclasses implement ``_open() -> fps`` (open the source; fps in frames per *host*
    second), ``_grab() -> (image, reference_force_n[, file_index]) or None`` (None: the
    stream ended, after calling :meth:`_end`; ``file_index``: the frame's row in the file
    the camera plays, :attr:`Frame.file_index`), ``_release()``, and may override
    ``_mode_hint()``, ``_disconnect_hint()`` and ``_pace_delay_s()``. ``_grab`` is called once in
    :meth:`connect` (to verify the frame size) and then on the reader thread.

    requested: (width, height) px to verify the frames against (None: any).
    live: True for live cameras (count timestamp gaps, drop the oldest frame when the
    queue is full); False for files (no gap accounting, the reader waits when the queue
    is full). paced: hold each frame until its time at ``fps`` on ``clock``.
    """

    channel_order = "BGR"

    def __init__(
        self,
        name: str,
        requested: tuple[int | None, int | None] = (None, None),
        *,
        queue_frames: int = DEFAULT_QUEUE_FRAMES,
        live: bool = True,
        paced: bool = False,
        clock: SimClock | None = None,
    ):
        if queue_frames < 1:
            raise ValueError(f"queue_frames must be >= 1, got {queue_frames}")
        self.name = name
        self.requested = requested
        self.live = live
        self.paced = paced
        self.clock = clock if clock is not None else SimClock()
        self.width = 0
        self.height = 0
        self.fps = DEFAULT_FPS
        self._queue: deque[Frame] = deque()
        self._queue_frames = int(queue_frames)
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._returned_index = -1  # newest index handed out by any read
        self._reader: ReaderThread | None = None
        self._stop = threading.Event()  # the running reader's stop event
        self._first: Captured | None = None  # grabbed by connect(), delivered first
        self._ended = False
        self._finite_end = False
        self._end_reason = "stopped delivering frames"
        self._captured = self._delivered = self._dropped = self._overflowed = self._skipped = 0
        self._last_capture_mono: float | None = None
        self._gap_report_s = -math.inf  # capture clock of the last gap line
        self._gaps = [0, 0, 0.0]  # gaps, frames lost, longest gap s since that line
        self._last_t_unix = -math.inf
        self._truth = FrameTruth(name)

    # --- subclass hooks -----------------------------------------------------------------
    def _open(self) -> float:
        raise NotImplementedError

    def _grab(self) -> Captured | None:
        raise NotImplementedError

    def _release(self) -> None:
        pass

    def _mode_hint(self) -> str:
        return "pass width=None, height=None to accept the frames' size"

    def _disconnect_hint(self) -> str | None:
        return None

    def _pace_delay_s(self) -> float:
        """Extra wait before the next paced frame (clock seconds); a stall fault."""
        return 0.0

    def _end(self, reason: str, *, finite: bool = False) -> None:
        """Record why the stream ends (``finite``: the normal end of a file); returns None
        so a ``_grab`` can ``return self._end(...)``."""
        self._end_reason = reason
        self._finite_end = finite

    # --- lifecycle --------------------------------------------------------------------
    def connect(self) -> None:
        """Open the source, check its first frame's size, then start the reader thread.

        Does nothing once connected, even after the stream ended (the frames still
        queued stay readable): ``close()`` then ``connect()`` to reconnect.
        """
        if self._reader is not None:
            return
        self._finite_end = False
        fps = self._open()
        try:
            first = self._grab()
            if first is None:
                raise DeviceNotConnectedError(
                    self.name, "opened but delivered no frame", self._disconnect_hint()
                )
            image = check_image(self.name, first[0])
            height, width = image.shape[:2]
            verify_mode(self.name, self.requested, (width, height), self._mode_hint())
        except BaseException:
            self._release()
            raise
        self.width, self.height, self.fps = width, height, fps
        self._first = (image, *first[1:])
        with self._cond:  # a reconnect starts a fresh stream; indices keep counting up
            self._queue.clear()
            self._latest = None
            self._last_capture_mono = None
            self._ended = False
            self._truth.restart(fps)
        self._reader = ReaderThread(f"{self.name} reader", self._run)
        self._stop = self._reader.stop_event
        self._reader.start()
        logger.info("%s: %dx%d at %.3g fps", self.name, self.width, self.height, self.fps)

    def close(self) -> None:
        """Stop the reader and release the device. Safe to call twice."""
        reader, self._reader = self._reader, None
        self._stop.set()
        with self._cond:
            if not self._ended:
                self._end("was closed")
            self._cond.notify_all()
        if reader is not None:
            reader.stop()
        self._release()

    @property
    def connected(self) -> bool:
        return self._reader is not None

    @property
    def stats(self) -> CameraStats:
        with self._cond:
            truth = self._truth
            return CameraStats(
                self._captured,
                self._delivered,
                self._dropped,
                self._overflowed,
                self._skipped,
                truth.duplicated,
                truth.delivered_fps,
                truth.requested_fps,
                truth.slow,
            )

    @property
    def ended(self) -> bool:
        """True once the reader stopped (end of file, unplugged) - frames may still be queued."""
        return self._ended

    # --- reading ----------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> Frame:
        """The next frame in capture order (waits up to ``timeout_s``)."""
        deadline = time.monotonic() + self._timeout(timeout_s)
        with self._cond:
            while not self._queue:
                self._wait(deadline, timeout_s)
            return self._hand_out([self._queue.popleft()])[0]

    def async_read(
        self, timeout_s: float | None = None, max_frames: int | None = None
    ) -> list[Frame]:
        """Every frame captured since the last read, oldest first (waits up to
        ``timeout_s`` for one); only the newest ``max_frames`` when more came (the older
        ones are skipped and counted)."""
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        deadline = time.monotonic() + self._timeout(timeout_s)
        with self._cond:
            while not self._queue:
                self._wait(deadline, timeout_s)
            frames = list(self._queue)
            self._queue.clear()
            if max_frames is not None and len(frames) > max_frames:
                self._skipped += len(frames) - max_frames
                frames = frames[-max_frames:]
            return self._hand_out(frames)

    def read_latest(self, timeout_s: float | None = None) -> Frame:
        """The newest frame, never one handed out before: waits for a new one if needed.

        Older queued frames are discarded (counted as ``skipped``).
        """
        deadline = time.monotonic() + self._timeout(timeout_s)
        with self._cond:
            while self._latest is None or self._latest.index <= self._returned_index:
                self._wait(deadline, timeout_s)
            frame = self._latest
            self._skipped += sum(1 for f in self._queue if f.index < frame.index)
            self._queue.clear()
            return self._hand_out([frame])[0]

    def _hand_out(self, frames: list[Frame]) -> list[Frame]:
        """Count ``frames`` (condition held) as delivered and wake a waiting file reader."""
        self._returned_index = frames[-1].index
        self._delivered += len(frames)
        self._cond.notify_all()
        return frames

    def _timeout(self, timeout_s: float | None) -> float:
        if timeout_s is not None:
            return float(timeout_s)
        return max(MIN_READ_TIMEOUT_S, 10.0 / self.fps if self.fps > 0 else MIN_READ_TIMEOUT_S)

    def _wait(self, deadline: float, timeout_s: float | None) -> None:
        """Wait on the condition (held) for news; raise if the stream is over or too late."""
        if self._ended:
            error = CameraEndedError if self._finite_end else CameraDisconnectedError
            raise error(
                self.name,
                f"{self._end_reason} after {self._captured} frames",
                None if self._finite_end else self._disconnect_hint(),
            )
        if self._reader is None:
            raise DeviceNotConnectedError(
                self.name, "not connected", "call connect() or use 'with'"
            )
        wait_or_time_out(
            self._cond,
            deadline,
            self.name,
            f"no new frame within {self._timeout(timeout_s):g} s (expected {self.fps:g} fps)",
            "is the camera still plugged in and lit?",
        )

    # --- reader thread ------------------------------------------------------------------
    def _run(self, stop: threading.Event) -> None:
        pacer = Pacer(self.fps / self.clock.time_scale, self.clock) if self.paced else None
        try:
            while not stop.is_set():
                if pacer is not None and not pacer.wait(stop, self._pace_delay_s()):
                    break
                if self._first is not None:  # the frame connect() grabbed to check the size
                    captured, self._first = self._first, None
                else:
                    captured = self._grab()
                t_unix, t_mono = self.clock.stamp()
                if captured is None or stop.is_set():
                    break
                self._push(check_image(self.name, captured[0]), captured[1:], t_unix, t_mono)
        except Exception as e:  # noqa: BLE001 - a backend failure ends the stream, with its reason
            logger.exception("%s: capture failed", self.name)
            self._end(f"capture failed ({e})")
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()
            if not stop.is_set():
                logger.warning(
                    "%s: %s after %d frames", self.name, self._end_reason, self._captured
                )

    def _push(self, image: np.ndarray, extra: tuple, t_unix: float, t_mono: float) -> None:
        """Queue a captured frame; ``extra``: (reference_force_n[, file_index])."""
        with self._cond:
            self._truth.add(image, t_mono)  # a file's repeated frames are a camera's too
            if self.live:
                self._count_gap(t_mono)
            else:
                while len(self._queue) >= self._queue_frames and not self._stop.is_set():
                    self._cond.wait(QUEUE_FULL_POLL_S)
            self._last_t_unix = max(t_unix, self._last_t_unix + MIN_TIMESTAMP_STEP_S)
            frame = Frame(
                image, self._captured, t_mono, self._last_t_unix, self.channel_order, *extra
            )
            self._captured += 1
            if len(self._queue) >= self._queue_frames:
                self._queue.popleft()
                self._overflowed += 1
            self._queue.append(frame)
            self._latest = frame
            self._cond.notify_all()

    def _count_gap(self, t_mono: float) -> None:
        last, self._last_capture_mono = self._last_capture_mono, t_mono
        if last is None or self.fps <= 0:
            return
        gap_s = t_mono - last
        if gap_s > GAP_FACTOR / self.fps:
            lost = max(1, round(gap_s * self.fps) - 1)
            self._dropped += lost
            self._report_gap(t_mono, gap_s, lost)

    def _report_gap(self, t_mono: float, gap_s: float, lost: int) -> None:
        """The first gap at once, then one line per :data:`GAP_REPORT_S` with the counts."""
        gaps = self._gaps
        gaps[0], gaps[1], gaps[2] = gaps[0] + 1, gaps[1] + lost, max(gaps[2], gap_s)
        if t_mono - self._gap_report_s < GAP_REPORT_S:
            return
        if gaps[0] == 1:
            logger.warning(
                "%s: %.0f ms capture gap, ~%d frame(s) dropped", self.name, gap_s * 1e3, lost
            )
        else:
            logger.warning(
                "%s: %d capture gaps in the last %.0f s, ~%d frame(s) dropped, longest %.0f ms",
                self.name,
                gaps[0],
                min(t_mono - self._gap_report_s, 99999),
                gaps[1],
                gaps[2] * 1e3,
            )
        self._gap_report_s, self._gaps = t_mono, [0, 0, 0.0]
