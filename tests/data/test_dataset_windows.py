"""Dataset windows (data/windows.py): the window of frames and, for a rest-referenced model,
its rest image in front, read the same way for training and evaluation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from beadsight.data.dataset import open_dataset
from beadsight.data.rest import REST_FRAMES, REST_MAX_FORCE_N, rest_ends
from beadsight.data.splits import dataset_window_ends
from beadsight.data.windows import RestImages, WindowReader, read_window, read_windows

SPAN = 15


def test_read_windows(make_dataset):
    data = make_dataset(presses=3, frames_per_press=30)
    with open_dataset(data) as ds:
        ends = np.array([20, 21, 50, 89])
        windows = read_windows(ds, ends, SPAN)
        assert windows.shape == (4, SPAN, 64, 64, 3) and windows.dtype == np.uint8
        for k, e in enumerate(ends):
            np.testing.assert_array_equal(windows[k], ds.read_frames(e - 14, e + 1))


def test_window_reader_reuses_overlap(make_dataset):
    data = make_dataset(presses=3, frames_per_press=30)
    with open_dataset(data) as ds:
        reader = WindowReader(ds, SPAN)
        reads = []
        original = ds.read_frames
        ds.read_frames = lambda a, b: reads.append((a, b)) or original(a, b)
        batches = [np.array([14, 15, 16]), np.array([17, 18, 40]), np.array([41, 70, 89])]
        for ends in batches:
            windows = reader(ends)
            for k, e in enumerate(ends):
                np.testing.assert_array_equal(windows[k], original(e - 14, e + 1))
        # Frames 3..16 are kept from the first batch; only new frames are read.
        assert reads[:2] == [(0, 17), (17, 19)]
        assert sum(b - a for a, b in reads) == len(
            set().union(*(range(e - 14, e + 1) for ends in batches for e in ends))
        )


def _area(frames: np.ndarray, size: int) -> np.ndarray:
    return np.stack([cv2.resize(f, (size, size), interpolation=cv2.INTER_AREA) for f in frames])


def test_rest_inputs_follow_the_rule_at_the_model_size(make_dataset):
    """Each input: the mean of the REST_FRAMES unloaded frames ending at rest_ends (each
    resized like the window first, the mean rounded), then the window oldest first; the
    random-access reader of training and the batch reader of evaluation agree."""
    data = make_dataset(presses=4, frames_per_press=40)
    with open_dataset(data) as ds:
        rests = rest_ends(ds.force_n, ds.valid)
        ends = dataset_window_ends(ds, SPAN, rest=True)
        assert ends.size and (rests[ends] >= 0).all()
        assert not np.isin(np.flatnonzero(ds.press_id == 0), ends).any()  # no rest before it
        picks = ends[[0, 1, ends.size // 2, -1]]
        got = WindowReader(ds, SPAN, 32, rest=True)(picks)
        assert got.shape == (4, 1 + SPAN, 32, 32, 3) and got.dtype == np.uint8
        for k, e in enumerate(picks.tolist()):
            r = int(rests[e])
            rest_frames = slice(r - REST_FRAMES + 1, r + 1)
            assert (ds.force_n[rest_frames] <= REST_MAX_FORCE_N).all()
            mean = _area(ds.read_frames(r - REST_FRAMES + 1, r + 1), 32).astype(np.float64)
            np.testing.assert_array_equal(got[k, 0], np.rint(mean.mean(axis=0)).astype(np.uint8))
            np.testing.assert_array_equal(got[k, 1:], _area(ds.read_frames(e - 14, e + 1), 32))
            np.testing.assert_array_equal(read_window(ds, e, SPAN, 32, r), got[k])
        # presses 1 and 3 are preceded by different unloaded runs: different rest images
        assert rests[picks[0]] != rests[picks[-1]]
        assert not np.array_equal(got[0, 0], got[-1, 0])


def test_rest_images_are_read_once_and_frames_without_one_are_refused(make_dataset):
    data = make_dataset(presses=3, frames_per_press=40)
    with open_dataset(data) as ds:
        images = RestImages(ds)
        reads = []
        original = ds.read_frames
        ds.read_frames = lambda a, b: reads.append((a, b)) or original(a, b)
        ends = dataset_window_ends(ds, SPAN, rest=True)
        one_rest = ends[
            rest_ends(ds.force_n, ds.valid)[ends] == rest_ends(ds.force_n, ds.valid)[ends[0]]
        ]
        images(one_rest[:3])
        images(one_rest[3:6])
        assert len(reads) == 1 and reads[0][1] - reads[0][0] == REST_FRAMES
        assert images.has_rest(np.array([0, 39, int(ends[0])])).tolist() == [False, False, True]
        with pytest.raises(ValueError, match=r"tiny\.h5: frame 20 has no rest image before it"):
            images(np.array([int(ends[0]), 20]))
        with pytest.raises(ValueError, match="frame 20 has no rest image"):
            WindowReader(ds, SPAN, rest=True)(np.array([20]))
