"""Recording videos -> preprocessed dataset frames, streamed with bounded memory.

Frames are read chunk by chunk in dataset order by one reader thread and pushed
through a :class:`~beadsight.preprocess.Preprocessor` on a thread pool (OpenCV
releases the GIL); for MJPG video the JPEGs are decoded by the workers, at reduced
size when the output does not need full resolution. The finished frames go to a
:class:`~beadsight.data.dataset_writer.DatasetWriter` in batches, with their labels.
"""

from __future__ import annotations

import collections
import os
import queue
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import numpy as np
from tqdm import tqdm

from beadsight.config import ConfigError
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.process.config import DECODE_SCALES, ProcessConfig
from beadsight.data.process.frame_labels import FrameLabels
from beadsight.data.recording import Recording, RecordingError, iter_video
from beadsight.preprocess import Preprocessor

DECODE_FLAGS = dict(
    zip(
        DECODE_SCALES,
        (
            cv2.IMREAD_COLOR,
            cv2.IMREAD_REDUCED_COLOR_2,
            cv2.IMREAD_REDUCED_COLOR_4,
            cv2.IMREAD_REDUCED_COLOR_8,
        ),
        strict=True,
    )
)
INFLIGHT_PER_WORKER = 4  # frames queued per preprocessing thread

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


def choose_decode(
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


def input_hw(rec: Recording) -> tuple[int, int]:
    if rec.frame_hw is not None:
        return rec.frame_hw
    for video in rec.videos.values():
        for image in iter_video(video):
            return image.shape[:2]
    raise RecordingError(f"{rec.path}: no readable video frames")


class _Batches:
    """Collects preprocessed frames and appends them with their labels in batches."""

    def __init__(self, writer: DatasetWriter, labels: FrameLabels, size: int):
        self.writer, self.labels, self.size = writer, labels, size
        self.rows: list[int] = []
        self.images: list[np.ndarray] = []
        self.written = 0

    def add(self, row: int, image: np.ndarray) -> None:
        self.rows.append(row)
        self.images.append(image)
        if len(self.rows) >= self.size:
            self.flush()

    def flush(self) -> None:
        if not self.rows:
            return
        rows, labels = np.asarray(self.rows), self.labels
        self.writer.append(
            np.stack(self.images),
            labels.force_n[rows],
            labels.position_mm[rows],
            labels.valid[rows],
            labels.t_unix[rows],
        )
        self.written += len(rows)
        self.rows.clear()
        self.images.clear()


def stream_frames(
    rec: Recording,
    order: np.ndarray,
    labels: FrameLabels,
    decode: tuple[bool, int, Preprocessor],
    writer: DatasetWriter,
    config: ProcessConfig,
    stats: dict[str, int],
    progress: bool,
) -> int:
    """Preprocess the logged frames ``order`` (rows of ``rec.frames``) into ``writer``.

    decode: (packets, factor, preprocessor) from :func:`choose_decode`. Counts frames
    missing from the videos or undecodable in ``stats``. returns: frames written.
    """
    packets, factor, pre = decode
    workers = config.workers or os.cpu_count() or 1
    inflight_max = workers * INFLIGHT_PER_WORKER
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
    batches = _Batches(writer, labels, config.batch_frames)
    bar = tqdm(total=len(order), unit="frame", desc="process", disable=not progress)
    try:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="beadsight-pre") as pool:
            producer.start()
            _pump(q, pool, work, inflight_max, batches, bar, stats)
            batches.flush()
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
    return batches.written


def _pump(q, pool, work, inflight_max, batches: _Batches, bar, stats) -> None:
    """Move frames from the reader queue through the pool into ``batches``, in order."""
    pending: collections.deque[tuple[int, Future]] = collections.deque()
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
            batches.add(row, image)
