"""Raw recordings: this project's writer/reader, the reference format, crash tolerance."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from helpers.recording import (
    CENTRE,
    T0_MONO,
    T0_UNIX,
    Timeline,
    frame_level,
    write_beadsight_raw,
    write_reference_raw,
)

from beadsight.data.recording import (
    RAW_FORMAT,
    REFERENCE_RAW_FORMAT,
    RecordingError,
    RecordingWriter,
    detect_format,
    is_mjpg,
    iter_video,
    open_recording,
)


def test_beadsight_roundtrip(tmp_path):
    tl = Timeline(presses=2)
    raw = write_beadsight_raw(tmp_path / "raw", tl, chunk_frames=30)
    rec = open_recording(raw)
    n = len(tl.frame_times())
    assert rec.format == RAW_FORMAT
    assert rec.warnings == []
    assert len(rec.frames) == n
    assert sorted(rec.videos) == list(range(int(np.ceil(n / 30))))
    assert rec.frame_hw == (96, 120) and rec.fps == 30.0
    # full float64 precision survives the CSV
    np.testing.assert_array_equal(rec.frames.t_unix, T0_UNIX + tl.frame_times())
    np.testing.assert_array_equal(rec.frames.t_mono, T0_MONO + tl.frame_times())
    np.testing.assert_array_equal(rec.frames.chunk, np.arange(n) // 30)
    np.testing.assert_array_equal(rec.frames.index, np.arange(n) % 30)
    assert rec.has_monotonic
    assert len(rec.force) == len(tl.force_times())
    np.testing.assert_allclose(rec.force.force_n, tl.force_n(tl.force_times()), atol=0.01)
    cmds = tl.commands()
    assert len(rec.moves) == len(cmds)
    assert rec.moves.gcode[0] == "G28"
    np.testing.assert_array_equal(rec.moves.is_data, [c[5] >= 0 for c in cmds])
    np.testing.assert_allclose(rec.moves.offset_mm[2], tl.xy[0])
    assert rec.completed_presses() == {0, 1}
    meta = json.loads((raw / "session.json").read_text())
    assert meta["status"] == "complete" and meta["frames"] == n
    # video content and packet access
    levels = [int(f.mean()) for f in iter_video(rec.videos[1])]
    assert levels == pytest.approx([frame_level(k) for k in range(30, 60)], abs=2)
    assert is_mjpg(rec.videos[0])
    packet = next(iter_video(rec.videos[0], packets=True))
    assert packet.dtype == np.uint8 and packet[:2].tobytes() == b"\xff\xd8"


@pytest.mark.parametrize("absolute", [False, True])
def test_reference_format(tmp_path, absolute):
    tl = Timeline(presses=2)
    raw = write_reference_raw(tmp_path / "ref", tl, absolute_xy=absolute)
    assert detect_format(raw) == REFERENCE_RAW_FORMAT
    rec = open_recording(raw)
    n = len(tl.frame_times())
    assert len(rec.frames) == n and sorted(rec.videos) == [0, 1]
    np.testing.assert_array_equal(rec.frames.t_unix, T0_UNIX + tl.frame_times())
    assert np.isnan(rec.frames.t_mono).all() and not rec.has_monotonic
    np.testing.assert_array_equal(rec.frames.camera_index, np.arange(n))
    np.testing.assert_allclose(rec.force.force_n, tl.force_n(tl.force_times()), atol=0.01)
    cmds = tl.commands()
    np.testing.assert_array_equal(rec.moves.is_data, [c[5] >= 0 for c in cmds])
    np.testing.assert_array_equal(rec.moves.press, [c[5] for c in cmds])
    data = rec.moves.is_data
    expected = np.array([(c[2] - CENTRE[0], c[3] - CENTRE[1]) for c in cmds])[data]
    np.testing.assert_allclose(rec.moves.offset_mm[data], expected, atol=1e-9)
    assert np.isnan(rec.moves.offset_mm[~data]).all()
    assert rec.centre_xy_mm == CENTRE
    first = next(iter_video(rec.videos[0]))
    assert first.shape == (96, 120, 3)
    assert not is_mjpg(rec.videos[0])  # XVID


def test_truncated_last_lines_are_dropped_and_reported(tmp_path):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=1))
    clean = open_recording(raw)
    for name, torn in [
        ("frames.csv", "9,3,1700000005.1"),
        ("force.csv", "1700000004.9,50"),
        ("printer.csv", "1700000005.0,5005.0,G1 X1"),
        ("events.jsonl", '{"ev'),
    ]:
        with open(raw / name, "a") as f:
            f.write(torn)
    rec = open_recording(raw)
    assert len(rec.frames) == len(clean.frames)
    assert len(rec.force) == len(clean.force)
    assert len(rec.moves) == len(clean.moves)
    assert len(rec.events) == len(clean.events)
    text = "\n".join(rec.warnings)
    for name in ("frames.csv", "force.csv", "printer.csv", "events.jsonl"):
        assert f"{name}: last record is truncated" in text


def test_truncated_video_chunk_reads_what_is_there(tmp_path):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=1), chunk_frames=60)
    last = max(open_recording(raw).videos.items())[1]
    full = sum(1 for _ in iter_video(last))
    data = last.read_bytes()
    last.write_bytes(data[: len(data) // 2])
    got = [int(f.mean()) for f in iter_video(last)]
    assert 0 < len(got) < full


def test_writer_refuses_nonempty_folder_and_bad_frames(tmp_path):
    (tmp_path / "raw").mkdir()
    (tmp_path / "raw" / "other.txt").write_text("x")
    with pytest.raises(RecordingError, match="not empty"):
        RecordingWriter(tmp_path / "raw", {}, frame_hw=(8, 8), fps=30)
    w = RecordingWriter(tmp_path / "new", {}, frame_hw=(8, 8), fps=30)
    with pytest.raises(RecordingError, match=r"\(8, 8, 3\) uint8"):
        w.write_frame(np.zeros((8, 9, 3), np.uint8), t_unix=1.0, t_mono=1.0, camera_index=0)
    w.close()
    with pytest.raises(RecordingError, match="already closed"):
        w.write_frame(np.zeros((8, 8, 3), np.uint8), t_unix=1.0, t_mono=1.0, camera_index=0)


def test_resume_appends_and_cuts_torn_tail(tmp_path):
    raw = tmp_path / "raw"
    w = RecordingWriter(raw, {"plan": {"seed": 3}}, frame_hw=(16, 16), fps=10, chunk_frames=4)
    for k in range(6):
        w.write_frame(np.full((16, 16, 3), 100, np.uint8), t_unix=1e9 + k, t_mono=k, camera_index=k)
    w.close("interrupted")
    with open(raw / "frames.csv", "a") as f:
        f.write("1,2,100000")  # a crash mid-line
    w = RecordingWriter(raw, {}, frame_hw=(16, 16), fps=10, chunk_frames=4, resume=True)
    for k in range(6, 9):
        w.write_frame(np.full((16, 16, 3), 100, np.uint8), t_unix=1e9 + k, t_mono=k, camera_index=k)
    w.close()
    rec = open_recording(raw)
    assert rec.warnings == []
    np.testing.assert_array_equal(rec.frames.camera_index, np.arange(9))
    np.testing.assert_array_equal(rec.frames.chunk, [0, 0, 0, 0, 1, 1, 2, 2, 2])
    assert rec.metadata["plan"] == {"seed": 3}
    assert [s["status"] for s in rec.metadata["sessions"]] == ["interrupted", "complete"]


def test_open_errors(tmp_path):
    with pytest.raises(RecordingError, match="not found"):
        open_recording(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="not a raw recording"):
        open_recording(tmp_path / "empty")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "session.json").write_text('{"format": "something-else"}')
    (bad / "frames.csv").write_text("chunk,index,t_unix,t_mono,camera_index\n")
    with pytest.raises(RecordingError, match=r"session\.json: field 'format'"):
        open_recording(bad)


def test_file_size_limit_gives_clear_error_and_keeps_data(tmp_path):
    """A writer that hits RLIMIT_FSIZE (as on a full disk) raises RecordingError naming
    the problem; chunks closed before stay readable."""
    raw = tmp_path / "raw"
    script = textwrap.dedent(f"""
        import resource, signal, sys
        import numpy as np
        from beadsight.data.recording import RecordingWriter, RecordingError
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))
        rng = np.random.default_rng(0)
        w = RecordingWriter({str(raw)!r}, {{}}, frame_hw=(64, 64), fps=10, chunk_frames=5)
        try:
            for k in range(10_000):
                w.write_frame(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8),
                              t_unix=1e9 + k, t_mono=float(k), camera_index=k)
        except RecordingError as e:
            print("ERROR", e)
            try:
                w.close("error")
            except RecordingError:
                pass
            sys.exit(3)
        sys.exit(0)
    """)
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 3, res.stdout + res.stderr
    assert "file size limit reached" in res.stdout or "disk full" in res.stdout
    rec = open_recording(raw)
    assert len(rec.frames) >= 5
    complete_chunks = [k for k, v in rec.videos.items() if sum(1 for _ in iter_video(v)) == 5]
    assert complete_chunks  # whole chunks written before the failure are readable
