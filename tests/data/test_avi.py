"""Why raw recordings use their own MJPG muxer: on a real full disk, OpenCV's writer loses
frames without a word, ours raises at once. Also: our AVI files read back in OpenCV."""

from __future__ import annotations

import errno
import os

import cv2
import numpy as np
import pytest

from beadsight.data.recording import MjpgAviWriter, RecordingError, RecordingWriter, iter_video

SIDE = 128  # random 128x128 frames: ~12 KB as JPEG, far more than the room left below
ROOM_LEFT = 24 * 1024  # bytes left free on the small disk before writing video


def _fill(disk, leave: int) -> None:
    st = os.statvfs(disk)
    (disk / "filler").write_bytes(b"x" * max(st.f_bavail * st.f_frsize - leave, 0))


def _frames(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (SIDE, SIDE, 3), dtype=np.uint8) for _ in range(n)]


def _readable(path) -> int:
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    return n


def test_opencv_videowriter_reports_success_but_loses_frames_on_a_full_disk(full_disk):
    """The claim behind MjpgAviWriter, checked: every write returns True and release()
    raises nothing, yet the file holds fewer frames than were written (no index, cut
    short). If a future OpenCV reports this, the muxer may give way to cv2.VideoWriter."""
    _fill(full_disk, ROOM_LEFT)
    path = full_disk / "cv2.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (SIDE, SIDE))
    assert writer.isOpened()
    results = [writer.write(frame) for frame in _frames(3)]
    writer.release()  # returns None: no way to learn that the tail was lost
    assert all(r is None or r is True for r in results)
    assert _readable(path) < 3


def test_our_muxer_raises_disk_full_at_once(full_disk):
    _fill(full_disk, ROOM_LEFT)
    writer = MjpgAviWriter(full_disk / "ours.avi", (SIDE, SIDE), 30.0)
    with pytest.raises(OSError) as info:
        for frame in _frames(3):
            writer.write(frame)
        writer.close()
    assert info.value.errno == errno.ENOSPC
    writer.close()  # safe after the failure


def test_our_avi_reads_back_in_opencv(tmp_path):
    frames = [np.full((48, 64, 3), level, np.uint8) for level in (30, 90, 150, 210)]
    writer = MjpgAviWriter(tmp_path / "a.avi", (48, 64), 25.0)
    for frame in frames:
        writer.write(frame)
    writer.close()
    cap = cv2.VideoCapture(str(tmp_path / "a.avi"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(25.0)
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 4
    cap.release()
    levels = [float(f.mean()) for f in iter_video(tmp_path / "a.avi")]
    assert levels == pytest.approx([30, 90, 150, 210], abs=2)


def test_recording_writer_on_a_full_disk_names_the_file_and_keeps_whole_chunks(full_disk):
    raw = full_disk / "raw"
    w = RecordingWriter(raw, {}, frame_hw=(SIDE, SIDE), fps=10, chunk_frames=2)
    with pytest.raises(RecordingError, match=r"video_\d{4}\.avi: write failed \(disk full\)"):
        for k, frame in enumerate(_frames(100)):
            w.write_frame(frame, t_unix=1e9 + k, t_mono=float(k), camera_index=k)
    with pytest.raises(RecordingError):
        w.close("error")  # session.json cannot be rewritten either: said, not hidden
    whole = [p for p in sorted(raw.glob("video_*.avi")) if _readable(p) == 2]
    assert whole  # chunks closed before the disk filled stay readable
