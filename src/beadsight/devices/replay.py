"""A dataset played as a camera: :class:`DatasetCamera` (``beadsight live --source FILE.h5``).

Plays the frames of a dataset file (this project's or the reference's processed layout,
whatever :func:`beadsight.data.dataset.open_dataset` reads) in row order, paced at the
file's fps (or the one given) like a video file, so live sensing runs on recorded or
simulated presses exactly as on a camera. Each frame carries what the file knows of it:

* ``reference_force_n``: the file's true force of that row, N; NaN where the row is not
  valid (the force and printer logs do not cover it: it has no truth, as ``evaluate``
  scores no such frame);
* ``file_index``: the row (:attr:`~beadsight.devices.Frame.file_index`), so a live
  recording maps back to the file (readings files record it as ``frame_index``).

Every row is played, invalid ones too (their images are real captures; only their labels
are missing). Where the file's timestamps show frames the recording camera dropped
(:func:`beadsight.data.timing.frame_breaks`), the replay waits the missing frames'
time (at most :data:`MAX_GAP_S`; :func:`replay_times_s`), so live sensing sees the gap a
live camera would have shown. Frames of another size than ``image_size`` are resized as the dataset's readers do
(area averaging, :func:`beadsight.data.windows.resize_frames`, as ``evaluate --resize``),
so live input is offline input. ``loop`` starts again at row 0 (``file_index`` too; the
capture ``index`` keeps counting up); otherwise the camera ends with
:class:`~beadsight.devices.CameraEndedError` after the last row.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np

from beadsight.devices.camera import DEFAULT_QUEUE_FRAMES, BufferedCamera, Captured
from beadsight.devices.clock import SimClock

logger = logging.getLogger(__name__)

DATASET_SUFFIXES = (".h5", ".hdf5")  # a --source with one of these is a dataset to replay
READ_BLOCK_FRAMES = 32  # rows read from the file at once (one HDF5 read per block)
MAX_GAP_S = 1.0  # the longest recorded capture gap the replay waits out, s


def replay_times_s(timestamp_s: np.ndarray, file_fps: float, fps: float) -> np.ndarray:
    """(N,) s: when each row is played, from the first, at ``fps``: one period per row, plus
    the recorded capture gap before a row where the file's timestamps show one
    (:func:`~beadsight.data.timing.frame_breaks`), at most :data:`MAX_GAP_S`.

    timestamp_s: (N,) the file's unix s; file_fps: the file's rate; fps: the replay's."""
    from beadsight.data.timing import frame_breaks

    t = np.asarray(timestamp_s, np.float64)
    step = np.full(len(t), 1.0 / fps)
    if len(t):
        step[0] = 0.0
        breaks = np.flatnonzero(frame_breaks(t, file_fps))
        missing = ((t[breaks] - t[breaks - 1]) * file_fps - 1.0) / fps  # at the replay rate
        missing = np.where(np.isfinite(missing), missing, 0.0)
        step[breaks] += np.clip(missing, 0.0, MAX_GAP_S)
    return np.cumsum(step)


def is_dataset_path(source: str | os.PathLike) -> bool:
    """True for a path naming a dataset file to replay (by its suffix: .h5, .hdf5)."""
    return Path(source).suffix.lower() in DATASET_SUFFIXES


class DatasetCamera(BufferedCamera):
    """The rows of dataset ``path`` as a camera (module docstring).

    image_size: the frames' size, px (S x S); None keeps the file's. fps: the replay rate
    (None: the file's ``fps``). realtime: pace frames at ``fps`` like a camera (False: as
    fast as they are read). loop: start again after the last row. Opening a file that is
    missing or not a dataset raises :class:`~beadsight.data.dataset.DatasetError` naming it.
    """

    channel_order = "RGB"

    def __init__(
        self,
        path: str | os.PathLike,
        image_size: int | None = None,
        fps: float | None = None,
        *,
        realtime: bool = True,
        loop: bool = False,
        queue_frames: int = DEFAULT_QUEUE_FRAMES,
        clock: SimClock | None = None,
        name: str | None = None,
    ):
        if fps is not None and not fps > 0:
            raise ValueError(f"dataset camera {path}: fps must be > 0, got {fps}")
        if image_size is not None and image_size < 1:
            raise ValueError(f"dataset camera {path}: image_size must be >= 1, got {image_size}")
        self.path = Path(path)
        super().__init__(
            name or f"dataset {self.path}",
            queue_frames=queue_frames,
            live=False,
            paced=realtime,
            clock=clock,
        )
        self.image_size = image_size
        self.requested_fps = fps
        self.loop = loop
        self._ds = None
        self._gaps_s = np.zeros(0)  # (rows,) the wait before each row beyond one period
        self._true_force = np.zeros(0)  # (rows,) N, NaN at invalid rows
        self._row = 0  # the next row to grab
        self._paced = 0  # frames paced so far (each is delivered in row order)
        self._block_start = 0
        self._block = np.zeros((0, 1, 1, 3), np.uint8)

    @property
    def rows(self) -> int:
        """Rows of the file (0 before :meth:`connect`)."""
        return len(self._true_force)

    # --- BufferedCamera hooks -----------------------------------------------------------
    def _open(self) -> float:
        from beadsight.data.dataset import DatasetError, open_dataset

        ds = open_dataset(self.path)
        if len(ds) == 0:
            ds.close()
            raise DatasetError(f"{self.path}: the dataset has no frames to replay")
        self._ds = ds
        self._true_force = np.where(ds.valid, ds.force_n, math.nan)
        fps = float(self.requested_fps or ds.fps)
        self._gaps_s = np.diff(replay_times_s(ds.timestamp_s, ds.fps, fps), prepend=0.0)
        self._gaps_s = np.maximum(self._gaps_s - 1.0 / fps, 0.0)
        self._gaps_s[0] = 0.0
        self._row, self._block_start, self._paced = 0, 0, 0
        self._block = self._block[:0]
        logger.info(
            "%s: %d rows at %g fps (%d invalid, %d capture gaps)",
            self.name,
            len(ds),
            fps,
            int((~ds.valid).sum()),
            int((self._gaps_s > 0).sum()),
        )
        return fps

    def _grab(self) -> Captured | None:
        if self._row >= self.rows:
            if not (self.loop and self.rows > 0):
                return self._end("end of file", finite=True)
            logger.info("%s: end of file, looping", self.name)
            self._row = 0
        row = self._row
        self._row += 1
        return self._image(row), float(self._true_force[row]), row

    def _pace_delay_s(self) -> float:
        """The extra wait before the next frame (called once per frame, in row order): the
        recorded capture gap before its row, if any."""
        row = self._paced % max(self.rows, 1)
        self._paced += 1
        return float(self._gaps_s[row]) if row < len(self._gaps_s) else 0.0

    def _image(self, row: int) -> np.ndarray:
        """(S, S, 3) uint8 RGB of ``row``; rows are read a block at a time."""
        from beadsight.data.windows import resize_frames

        k = row - self._block_start
        if not 0 <= k < len(self._block):
            stop = min(row + READ_BLOCK_FRAMES, self.rows)
            block = self._ds.read_frames(row, stop)
            size = self.image_size or block.shape[1]
            self._block, self._block_start, k = resize_frames(block, size), row, 0
        return self._block[k]

    def _release(self) -> None:
        ds, self._ds = self._ds, None
        self._block = self._block[:0]
        if ds is not None:
            ds.close()

    def _mode_hint(self) -> str:
        return "a dataset camera delivers the file's frames at image_size"
