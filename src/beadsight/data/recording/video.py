"""Reading the videos of a raw session: frames, or the JPEG packets of MJPG video."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from beadsight.data.recording.logs import RecordingError
from beadsight.files import require_regular_file


def probe_video(path: Path) -> tuple[tuple[int, int] | None, float | None]:
    """((rows, cols), fps) of a video file; None where OpenCV cannot tell. A path that is
    not a regular file is a RecordingError (a FIFO would block OpenCV for ever)."""
    require_regular_file(path, RecordingError, "a video file")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            return None, None
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = cap.get(cv2.CAP_PROP_FPS)
        return ((h, w) if w > 0 and h > 0 else None), (fps if fps and fps > 0 else None)
    finally:
        cap.release()


def iter_video(path: str | Path, *, packets: bool = False) -> Iterator[np.ndarray]:
    """Frames of one video file in order.

    ``packets=False``: (H, W, 3) uint8 BGR images. ``packets=True``: the encoded JPEG of
    each frame as a 1-D uint8 array (MJPG only; decode with ``cv2.imdecode``, possibly
    at reduced size) -- raises RecordingError if the video is not MJPG. Stops at the
    end of the file or at the first undecodable frame (a truncated chunk).
    """
    require_regular_file(path, RecordingError, "a video file")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise RecordingError(f"{path}: cannot open video")
    try:
        if packets:
            cap.set(cv2.CAP_PROP_FORMAT, -1)
        while True:
            ok, item = cap.read()
            if not ok or item is None:
                return
            if packets:
                data = item.reshape(-1)
                if data[:2].tobytes() != b"\xff\xd8":
                    raise RecordingError(f"{path}: not an MJPG video (frames are not JPEG)")
                yield data.copy()
            else:
                yield item
    finally:
        cap.release()


def is_mjpg(path: str | Path) -> bool:
    """Whether a video's frames are JPEG images (readable as packets)."""
    try:
        next(iter_video(path, packets=True))
    except (RecordingError, StopIteration):
        return False
    return True
