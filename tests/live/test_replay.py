"""A dataset replayed as a camera (``live --source FILE.h5``): rows in order at the file's
rate with their true forces and rows, through the real live pipeline and CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.cli import run_beadsight
from helpers.live import TINY, TORCH, live_argv, tiny_model

from beadsight.data.dataset import DatasetError, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.windows import resize_frames
from beadsight.devices import CameraEndedError
from beadsight.devices.replay import MAX_GAP_S, DatasetCamera
from beadsight.live.recording.readings import open_readings
from beadsight.live.sensor import LiveSensor
from beadsight.live.sources import open_camera

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads

ROWS = 40
INVALID = (5, 6, 7)  # rows the logs do not cover
GAP_ROW = 20  # the recording camera lost 3 frames before this row
GAP_FRAMES = 3
LEVEL = 5  # grey level added per row, so each frame tells its row


def write_rows(path, fps: float = 40.0, rows: int = ROWS, size: int = 64):
    """A dataset whose row k is a flat frame of level ``LEVEL * k``, force ``0.1 k`` N."""
    frames = np.repeat((LEVEL * np.arange(rows, dtype=np.uint8))[:, None, None, None], size, 1)
    frames = np.ascontiguousarray(np.broadcast_to(frames[:, :, :1], (rows, size, size, 3)))
    force = 0.1 * np.arange(rows)
    valid = np.ones(rows, bool)
    valid[list(INVALID)] = False
    t = 1.7e9 + np.arange(rows) / fps
    t[GAP_ROW:] += GAP_FRAMES / fps
    with DatasetWriter(path, TINY.with_image_size(size), fps=fps) as w:
        w.append(frames, force, np.zeros((rows, 2)), valid, t)
    return path, force, valid


def play(camera) -> list:
    frames = []
    with camera:
        while True:
            try:
                frames.append(camera.read(timeout_s=5))
            except CameraEndedError:
                return frames


def test_dataset_camera_plays_rows_in_order_at_the_files_rate(tmp_path):
    path, force, valid = write_rows(tmp_path / "rows.h5")
    camera = open_camera(path, image_size=64)
    assert isinstance(camera, DatasetCamera) and camera.name == f"dataset {path}"
    frames = play(camera)
    assert camera.fps == 40.0 and camera.rows == ROWS
    assert [f.file_index for f in frames] == list(range(ROWS))
    assert [f.index for f in frames] == list(range(ROWS))
    assert all(f.channel_order == "RGB" and f.image.shape == (64, 64, 3) for f in frames)
    assert [int(f.image[0, 0, 0]) for f in frames] == [LEVEL * k for k in range(ROWS)]
    truth = [f.reference_force_n for f in frames]
    np.testing.assert_array_equal(truth, np.where(valid, force, np.nan))
    assert all(math.isnan(truth[k]) for k in INVALID)
    dt = np.diff([f.t_mono for f in frames])
    steady = np.delete(dt, GAP_ROW - 1)
    assert np.median(steady) == pytest.approx(1 / 40, abs=0.004)  # paced at the file's fps
    # the recorded capture gap is waited out (GAP_FRAMES frames more than one period)
    assert dt[GAP_ROW - 1] > (GAP_FRAMES + 0.5) / 40 and GAP_FRAMES / 40 < MAX_GAP_S
    assert (dt[GAP_ROW - 1] > dt).sum() >= len(dt) - 3  # the longest wait, but host jitter


def test_dataset_camera_loops_resizes_and_takes_an_fps(tmp_path):
    path, _, _ = write_rows(tmp_path / "rows.h5", rows=20, size=64)
    camera = DatasetCamera(path, image_size=32, fps=200.0, loop=True)
    with camera:
        frames = [camera.read(timeout_s=5) for _ in range(45)]
    assert camera.fps == 200.0
    assert [f.file_index for f in frames] == [k % 20 for k in range(45)]
    assert [f.index for f in frames] == list(range(45))  # capture order goes on
    with open_dataset(path) as ds:
        expected = resize_frames(ds.read_frames(0, len(ds)), 32)
    for f in frames:
        np.testing.assert_array_equal(f.image, expected[f.file_index])


def test_a_missing_or_hostile_dataset_source_names_the_file(tmp_path):
    missing = tmp_path / "missing.h5"
    with pytest.raises(DatasetError, match=r"missing\.h5: dataset file not found"):
        DatasetCamera(missing).connect()
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(DatasetError, match=r"notes\.h5: not a readable HDF5 file"):
        DatasetCamera(text).connect()
    with pytest.raises(ValueError, match=r"fps must be > 0"):
        DatasetCamera(text, fps=0)
    with pytest.raises(DatasetError, match=r"missing\.h5: dataset file not found"):
        LiveSensor(tiny_model(), missing, TORCH).open()  # what `live --source` opens


def test_live_cli_replays_a_dataset_to_its_end(tmp_path, caplog):
    path, force, valid = write_rows(tmp_path / "small.h5", fps=60.0, rows=60)
    checkpoint = tiny_model().save(tmp_path / "tiny.pt")
    out = tmp_path / "rec.h5"
    argv = live_argv(checkpoint, path, "--no-viewer", "--output", str(out))
    done = run_beadsight(*argv)  # in this process: a child would add only torch's import
    assert done.returncode == 0, done.stderr
    assert "end of file after 60 frames" in caplog.text  # the warning a child prints on stderr
    with open_readings(out) as rf:
        rows = rf.frame_index
        assert len(rf) >= 1 and rows[-1] == 59  # the file's last row ends the stream
        assert np.all(np.diff(rows) > 0) and rows[0] >= 14  # a full 15-frame window
        truth = np.where(valid, force, np.nan).astype(np.float32)
        np.testing.assert_array_equal(rf.reference_force_n, truth[rows])
        assert rf.provenance["source"] == f"dataset {path}"
