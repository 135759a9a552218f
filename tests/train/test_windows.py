"""Training windows: causality, labels, resizing, D4 exactness, batching and sharding."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from helpers.synthetic_presses import write_synthetic_dataset
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight.data.dataset import dataset_fingerprint, open_dataset
from beadsight.data.labels import label_maps
from beadsight.data.splits import dataset_window_ends, split_presses, window_ends
from beadsight.data.windows import WindowReader, pixel_stats
from beadsight.train.augment import D4_ORDER, d4_batch, d4_transform
from beadsight.train.windows import (
    DeviceFrames,
    DeviceWindows,
    WindowDataset,
    WindowLabels,
    WindowLoader,
    batches_per_epoch,
    choose_loader_mode,
    epoch_batches,
    window_frame_mask,
)

T = 15


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """One dataset for the module: the tests only read it."""
    path = write_synthetic_dataset(
        tmp_path_factory.mktemp("windows") / "tiny.h5", 6, 40, 64, 0, 30.0
    )
    with open_dataset(path) as ds:
        yield path, ds


def _labels(ds, size=None, presses=None):
    ends = window_ends(ds.press_id, ds.valid, T, presses=presses)
    return WindowLabels.from_dataset(ds, ends, size or ds.image_size)


def test_window_is_causal_and_labelled_by_its_newest_frame(tiny):
    path, ds = tiny
    labels = _labels(ds)
    windows = WindowDataset(path, labels, T)
    assert len(windows) == len(labels) > 0
    for i in (0, len(windows) // 2, len(windows) - 1):
        frames, target = windows[i]
        end = int(labels.ends[i])
        assert frames.shape == (T, 64, 64, 3) and frames.dtype == torch.uint8
        assert target.shape == (64, 64) and target.dtype == torch.float32
        np.testing.assert_array_equal(frames.numpy(), ds.read_frames(end - T + 1, end + 1))
        # oldest first: the last frame is the window's end frame, the label's frame
        np.testing.assert_array_equal(frames[-1].numpy(), ds.read_frames(end, end + 1)[0])
        expected = label_maps(
            ds.force_n[[end]], ds.position_mm[[end]], ds.contact[[end]], ds.geometry
        )[0]
        np.testing.assert_allclose(target.numpy(), expected, atol=1e-6)
        # every frame of the window is valid, and the frames follow each other in time
        assert ds.valid[end - T + 1 : end + 1].all()
        steps = np.diff(ds.timestamp_s[end - T + 1 : end + 1])
        np.testing.assert_allclose(steps, 1 / ds.fps, atol=1e-6)
    # the recording is continuous and every frame valid: every frame with T - 1 frames
    # before it ends a window, across press boundaries (issue 13 item 7)
    np.testing.assert_array_equal(labels.ends, np.arange(T - 1, len(ds)))
    # windows in contact have non-zero labels, windows out of contact zero
    some_contact = np.flatnonzero(labels.contact)[0]
    assert windows[int(some_contact)][1].sum() > 0


def test_reduced_image_size_resizes_frames_with_inter_area_and_renders_labels_at_size(tiny):
    path, ds = tiny
    labels = _labels(ds, size=32)
    frames, target = WindowDataset(path, labels, T)[3]
    end = int(labels.ends[3])
    raw = ds.read_frames(end - T + 1, end + 1)
    expected = np.stack([cv2.resize(f, (32, 32), interpolation=cv2.INTER_AREA) for f in raw])
    np.testing.assert_array_equal(frames.numpy(), expected)
    g32 = ds.geometry.with_image_size(32)
    np.testing.assert_allclose(
        target.numpy(),
        label_maps(ds.force_n[[end]], ds.position_mm[[end]], ds.contact[[end]], g32)[0],
        atol=1e-6,
    )


def test_device_mode_batches_equal_host_mode_items(tiny):
    path, ds = tiny
    labels = _labels(ds, size=32)
    mask = window_frame_mask(labels.ends, T, len(ds))
    store = DeviceFrames.load(ds, mask, 32, torch.device("cpu"), progress=False)
    assert store.frames.shape == (int(mask.sum()), 32, 32, 3)
    device = DeviceWindows(store, labels, T)
    host = WindowDataset(path, labels, T)
    idx = np.array([0, 5, len(labels) - 1, 17])
    frames, targets = device.batch(idx)
    for row, i in enumerate(idx):
        f, t = host[int(i)]
        np.testing.assert_array_equal(frames[row].numpy(), f.numpy())
        np.testing.assert_allclose(targets[row].numpy(), t.numpy(), atol=1e-4)


def test_rest_windows_are_the_evaluation_inputs_in_both_modes(tiny):
    """Training's rest-referenced windows (host and device mode) are the inputs evaluation
    reads for the same frames (data.windows.WindowReader): one builder."""
    path, ds = tiny
    ends = dataset_window_ends(ds, T, rest=True)
    labels = WindowLabels.from_dataset(ds, ends, 32, rest=True)
    store = DeviceFrames.load(ds, labels.frame_mask(T, len(ds)), 32, torch.device("cpu"), False)
    device, host = DeviceWindows(store, labels, T), WindowDataset(path, labels, T)
    idx = np.array([0, 5, len(labels) // 2, len(labels) - 1])
    frames, _ = device.batch(idx)
    expected = WindowReader(ds, T, 32, rest=True)(ends[idx])
    assert frames.shape == (4, 1 + T, 32, 32, 3)
    np.testing.assert_array_equal(frames.numpy(), expected)
    for row, i in enumerate(idx.tolist()):
        np.testing.assert_array_equal(host[i][0].numpy(), expected[row])
    with pytest.raises(ValueError, match="no rest frames before them"):
        WindowLabels.from_dataset(ds, window_ends(ds.press_id, ds.valid, T), 32, rest=True)


def test_window_frame_mask_covers_exactly_the_windows_frames():
    mask = window_frame_mask(np.array([20, 21, 50]), 5, 60)
    assert np.flatnonzero(mask).tolist() == [16, 17, 18, 19, 20, 21, 46, 47, 48, 49, 50]


@pytest.mark.parametrize("k", range(D4_ORDER))
def test_d4_matches_numpy_rot90_and_flip(k):
    rng = np.random.default_rng(k)
    frames = rng.integers(0, 256, (T, 8, 8, 3), dtype=np.uint8)
    target = rng.random((8, 8)).astype(np.float32)
    rot = np.rot90(frames, k % 4, axes=(1, 2))
    expected = np.flip(rot, axis=2) if k >= 4 else rot
    np.testing.assert_array_equal(d4_transform(frames, k, axes=(1, 2)), expected)
    rot_t = np.rot90(target, k % 4)
    expected_t = np.flip(rot_t, axis=1) if k >= 4 else rot_t
    np.testing.assert_array_equal(d4_transform(target, k), expected_t)
    # torch gives the same arrays
    np.testing.assert_array_equal(
        d4_transform(torch.from_numpy(frames), k, axes=(1, 2)).numpy(), expected
    )
    np.testing.assert_array_equal(d4_transform(torch.from_numpy(target), k).numpy(), expected_t)


def test_d4_gives_eight_distinct_symmetries_and_rejects_others():
    x = np.arange(16).reshape(4, 4)
    images = {d4_transform(x, k).tobytes() for k in range(D4_ORDER)}
    assert len(images) == 8
    with pytest.raises(ValueError, match="0..7"):
        d4_transform(x, 8)


def test_d4_batch_transforms_frames_and_target_identically_per_sample():
    rng = np.random.default_rng(0)
    # each sample's frames carry its target in every frame and channel, so a
    # transform applied identically keeps them equal
    targets = torch.from_numpy(rng.integers(0, 256, (16, 8, 8)).astype(np.float32))
    frames = targets.to(torch.uint8)[:, None, :, :, None].expand(16, 3, 8, 8, 3).contiguous()
    for ks in (rng.integers(0, 8, 16), np.sort(rng.integers(0, 8, 16))):  # general, sliced
        out_f, out_t = d4_batch(frames, targets, ks)
        for b in range(16):
            expected = d4_transform(targets[b].numpy(), ks[b])
            np.testing.assert_array_equal(out_t[b].numpy(), expected)
            for t in range(3):
                np.testing.assert_array_equal(out_f[b, t, ..., 1].numpy(), expected)


def test_loader_augments_train_batches_exactly_as_planned(tiny):
    path, ds = tiny
    labels = _labels(ds)
    host = WindowDataset(path, labels, T)
    loader = WindowLoader(
        host, 8, device=torch.device("cpu"), shuffle=True, augment=True, seed=3, num_workers=0
    )
    loader.set_epoch(2)
    plan = epoch_batches(len(labels), 8, epoch=2, seed=3, shuffle=True, augment=True)
    assert len(loader) == len(plan) == batches_per_epoch(len(labels), 8)
    seen_k = set()
    for (frames, targets), (idx, ks) in zip(loader, plan, strict=True):
        for row, (i, k) in enumerate(zip(idx, ks, strict=True)):
            f, t = host[int(i)]
            np.testing.assert_array_equal(frames[row].numpy(), d4_transform(f.numpy(), k, (1, 2)))
            np.testing.assert_allclose(targets[row].numpy(), d4_transform(t.numpy(), k))
            seen_k.add(int(k))
    assert seen_k == set(range(8))  # all 8 transforms are drawn, not only rotations
    # validation loaders do not augment and keep file order
    val = WindowLoader(host, 8, device=torch.device("cpu"), shuffle=False, augment=False)
    frames, targets = next(iter(val))
    np.testing.assert_array_equal(frames[0].numpy(), host[0][0].numpy())


@pytest.mark.timeout(180)
def test_host_loader_with_workers_matches_device_loader(tiny):
    path, ds = tiny
    # Use OpenCV's thread pool first: forked workers used to deadlock inheriting it.
    cv2.GaussianBlur(np.zeros((512, 512, 3), np.uint8), (0, 0), 3)
    labels = _labels(ds)
    mask = window_frame_mask(labels.ends, T, len(ds))
    store = DeviceFrames.load(ds, mask, 64, torch.device("cpu"), progress=False)
    kw = dict(device=torch.device("cpu"), shuffle=True, augment=True, seed=1)
    dev = WindowLoader(DeviceWindows(store, labels, T), 16, **kw)
    host = WindowLoader(WindowDataset(path, labels, T), 16, num_workers=2, **kw)
    assert (dev.mode, host.mode) == ("device", "host")
    for loader in (dev, host):
        loader.set_epoch(1, skip_batches=2)
    pairs = list(zip(dev, host, strict=True))
    assert len(pairs) == len(dev) - 2
    for (fa, ta), (fb, tb) in pairs:
        assert torch.equal(fa, fb)
        torch.testing.assert_close(ta, tb, atol=1e-4, rtol=1e-5)  # float32 vs float64 labels


def test_epoch_batches_are_seeded_and_shard_like_distributed_sampler():
    a = epoch_batches(23, 4, epoch=0, seed=0, shuffle=True, augment=True)
    b = epoch_batches(23, 4, epoch=0, seed=0, shuffle=True, augment=True)
    c = epoch_batches(23, 4, epoch=1, seed=0, shuffle=True, augment=True)
    flat = lambda plan: np.concatenate([i for i, _ in plan])  # noqa: E731
    assert np.array_equal(flat(a), flat(b)) and not np.array_equal(flat(a), flat(c))
    assert sorted(flat(a).tolist()) == list(range(23))
    shards = [
        epoch_batches(23, 4, epoch=0, seed=0, shuffle=True, augment=True, rank=r, world_size=2)
        for r in range(2)
    ]
    assert len(shards[0]) == len(shards[1]) == batches_per_epoch(23, 4, world_size=2)
    union = np.concatenate([flat(s) for s in shards])
    assert len(union) == 24 and set(union.tolist()) == set(range(23))  # padded by one
    # the same windows with the same transforms, whatever the world size
    pairs1 = {
        (int(i), int(k)) for i, k in zip(flat(a), np.concatenate([k for _, k in a]), strict=True)
    }
    pairs2 = {
        (int(i), int(k)) for s in shards for idx, ks in s for i, k in zip(idx, ks, strict=True)
    }
    assert pairs1 == pairs2


def test_splits_are_seeded_and_windows_end_in_their_presses(tiny):
    _, ds = tiny
    s0, s0b, s1 = (split_presses(ds.num_presses, seed=s) for s in (0, 0, 1))
    assert all(np.array_equal(s0[k], s0b[k]) for k in s0)
    assert any(not np.array_equal(s0[k], s1[k]) for k in s0)
    all_ids = np.concatenate([s0[k] for k in ("train", "val", "test")])
    assert sorted(all_ids.tolist()) == list(range(ds.num_presses))
    crossing = 0
    for name in ("train", "val", "test"):
        labels = _labels(ds, presses=s0[name])
        assert len(labels) > 0
        # a window belongs to the split of its end frame's press ...
        assert set(ds.press_id[labels.ends].tolist()) <= set(s0[name].tolist())
        # ... and every frame of that press with T - 1 frames before it ends one
        in_split = np.flatnonzero(np.isin(ds.press_id, s0[name]))
        np.testing.assert_array_equal(labels.ends, in_split[in_split >= T - 1])
        # its history may reach back into the previous press, never further
        frames = np.flatnonzero(window_frame_mask(labels.ends, T, len(ds)))
        allowed = set(s0[name].tolist()) | {p - 1 for p in s0[name].tolist()}
        assert set(ds.press_id[frames].tolist()) <= allowed
        starts = labels.ends - T + 1
        crossing += int((ds.press_id[starts] != ds.press_id[labels.ends]).sum())
    assert crossing > 0


def test_pixel_stats_and_fingerprint(tiny, make_dataset):
    path, ds = tiny
    mask = np.ones(len(ds), bool)
    mean, std = pixel_stats(ds, mask, 64, max_frames=10_000)
    pixels = ds.read_frames(0, len(ds)).reshape(-1, 3).astype(np.float64)
    np.testing.assert_allclose(mean, pixels.mean(0), rtol=1e-9)
    np.testing.assert_allclose(std, pixels.std(0), rtol=1e-6)
    assert dataset_fingerprint(ds) == dataset_fingerprint(ds)
    with open_dataset(make_dataset(seed=1, name="other.h5")) as other:
        assert dataset_fingerprint(other) != dataset_fingerprint(ds)


def test_choose_loader_mode():
    cpu = torch.device("cpu")
    assert choose_loader_mode("auto", 1_000, cpu) == "device"
    assert choose_loader_mode("auto", 1 << 60, cpu) == "host"
    assert choose_loader_mode("host", 1_000, cpu) == "host"
    assert choose_loader_mode("device", 1 << 60, cpu) == "device"
    with pytest.raises(ValueError, match="loader"):
        choose_loader_mode("gpu", 1, cpu)
