"""Training windows: causal stacks of ``span`` consecutive frames labelled by their newest
frame (the model sees ``frames`` of them, every ``frame_stride``-th).

A window ending at frame ``e`` holds frames ``e-span+1 .. e`` (oldest first); its
target is the ground-truth pressure map of frame ``e``
(:func:`beadsight.data.labels.label_maps`), so the model never sees the future.
Which frames may end a window comes from :func:`beadsight.data.splits.dataset_window_ends`,
the same selection evaluation uses.

Two ways to feed a training loop, with the same batches:

* **host** (:class:`WindowDataset` + a ``torch.utils.data.DataLoader`` with workers):
  each window is one contiguous slice read from the HDF5 file, resized on the fly
  (``cv2.INTER_AREA``) when training at a reduced image size, by
  :func:`beadsight.data.windows.read_window`, the builder evaluation uses too.
* **device** (:class:`DeviceWindows`): every frame any window needs is loaded once
  into one uint8 tensor on the training device (GPU memory or RAM); a batch is
  gathered by index arithmetic and labelled on the device, with no per-sample
  Python work.

:class:`WindowLoader` wraps either source; it shards batches across DDP ranks
like ``DistributedSampler``, applies the 8 dihedral (D4) transforms identically
to all frames of a window and its target, and is deterministic given
``(seed, epoch)`` so a resumed run sees the same batches it would have seen.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from beadsight.config import ConfigError, SensorGeometry
from beadsight.data.dataset import Dataset, open_dataset
from beadsight.data.labels import label_maps
from beadsight.data.rest import REST_FRAMES, rest_ends, rest_frame_mask
from beadsight.data.windows import read_window, resize_frames
from beadsight.train.augment import D4_ORDER, d4_batch, index_on
from beadsight.train.config import LOADER_MODES

logger = logging.getLogger(__name__)

DEVICE_MEMORY_FRACTION = (
    0.4  # "auto" keeps frames on a GPU when they fill <= this of its free memory
)
HOST_MEMORY_FRACTION = 0.5  # ... or in RAM (CPU training) when they fill <= this of available RAM
WORKER_START_METHOD = "spawn"  # host-mode DataLoader workers start as fresh processes
READ_BLOCK_FRAMES = 256  # frames per HDF5 read while loading frames into memory


# --- frames --------------------------------------------------------------------------
def window_frame_mask(ends: np.ndarray, span: int, num_frames: int) -> np.ndarray:
    """(N,) bool: frames that belong to at least one window (of ``span`` frames) ending at
    ``ends``."""
    delta = np.zeros(num_frames + 1, dtype=np.int64)
    np.add.at(delta, np.asarray(ends) - span + 1, 1)
    np.add.at(delta, np.asarray(ends) + 1, -1)
    return np.cumsum(delta[:-1]) > 0


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) ranges of consecutive True values."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()
    return list(zip(starts, stops, strict=True))


# --- window sources ----------------------------------------------------------------
@dataclass(frozen=True)
class WindowLabels:
    """What labels the windows of one split: end frames and their label inputs.

    ends: (M,) int64 frame index of each window's newest frame; force_n: (M,) N;
    position_mm: (M, 2) mm; contact: (M,) bool; geometry: at the training image size;
    rests: (M,) int64 last frame of each window's rest image (rest-referenced models,
    :func:`~beadsight.data.rest.rest_ends`), or None.
    """

    ends: np.ndarray
    force_n: np.ndarray
    position_mm: np.ndarray
    contact: np.ndarray
    geometry: SensorGeometry
    rests: np.ndarray | None = None

    @classmethod
    def from_dataset(
        cls, ds: Dataset, ends: np.ndarray, image_size: int, rest: bool = False
    ) -> WindowLabels:
        """Labels of the windows ending at ``ends`` (with their rest frames if ``rest``:
        every end must have one, as :func:`dataset_window_ends` with ``rest`` gives)."""
        ends = np.asarray(ends, dtype=np.int64)
        rests = rest_ends(ds.force_n, ds.valid)[ends] if rest else None
        if rests is not None and (rests < 0).any():
            raise ValueError(f"{ds.path}: some windows have no rest frames before them")
        return cls(
            ends=ends,
            force_n=ds.force_n[ends].astype(np.float64),
            position_mm=ds.position_mm[ends].astype(np.float64),
            contact=ds.contact[ends].astype(bool),
            geometry=ds.geometry.with_image_size(image_size),
            rests=rests,
        )

    def frame_mask(self, span: int, num_frames: int) -> np.ndarray:
        """(num_frames,) bool: the frames these windows (and their rest images) read."""
        mask = window_frame_mask(self.ends, span, num_frames)
        if self.rests is not None:
            mask |= rest_frame_mask(self.rests, num_frames)
        return mask

    def __len__(self) -> int:
        return len(self.ends)

    def maps(self, index: np.ndarray) -> np.ndarray:
        """(B,) window indices -> (B, S, S) float32 kPa targets (numpy)."""
        return label_maps(
            self.force_n[index], self.position_mm[index], self.contact[index], self.geometry
        )


class WindowDataset(torch.utils.data.Dataset):
    """Host-mode windows read from the HDF5 file (one contiguous slice per window).

    item ``i``: (images (inputs, S, S, 3) uint8 RGB: the rest image first if the labels
    have rests, then the window oldest first; target (S, S) float32 kPa),
    where S is ``labels.geometry.image_size_px`` (frames are resized with
    ``cv2.INTER_AREA`` if the file's frames are larger). The file is opened lazily
    in each process, so the dataset can go to DataLoader workers.
    """

    def __init__(self, path: str | Path, labels: WindowLabels, span: int):
        self.path = Path(path)
        self.labels = labels
        self.span = span
        self._ds: Dataset | None = None
        self._pid = -1

    def __len__(self) -> int:
        return len(self.labels)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_ds": None, "_pid": -1}

    def _dataset(self) -> Dataset:
        if self._ds is None or self._pid != os.getpid():
            self._ds = open_dataset(self.path)
            self._pid = os.getpid()
        return self._ds

    def read(self, i: int) -> np.ndarray:
        """(inputs, S, S, 3) uint8 RGB images of window ``i`` (rest image first, if any)."""
        rest = None if self.labels.rests is None else int(self.labels.rests[i])
        size = self.labels.geometry.image_size_px
        return read_window(self._dataset(), int(self.labels.ends[i]), self.span, size, rest)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        target = self.labels.maps(np.array([i]))[0]
        return torch.from_numpy(np.ascontiguousarray(self.read(i))), torch.from_numpy(target)

    def close(self) -> None:
        if self._ds is not None:
            self._ds.close()
            self._ds = None


class DeviceFrames:
    """The frames of a set of windows, loaded once into one uint8 tensor on ``device``.

    frames: (Nc, S, S, 3) uint8 RGB (only frames some window needs, in file order);
    compact: (N,) int64 position of each file frame in ``frames`` (-1 if not loaded).
    Consecutive frames of a window stay consecutive, so window ``e`` is
    ``frames[compact[e] - T + 1 : compact[e] + 1]``.
    """

    def __init__(self, frames: torch.Tensor, compact: np.ndarray):
        self.frames = frames
        self.compact = compact

    @classmethod
    def load(
        cls,
        ds: Dataset,
        frame_mask: np.ndarray,
        image_size: int,
        device: torch.device,
        progress: bool = True,
    ) -> DeviceFrames:
        n = int(frame_mask.sum())
        compact = np.full(len(frame_mask), -1, dtype=np.int64)
        compact[frame_mask] = np.arange(n)
        frames = torch.empty((n, image_size, image_size, 3), dtype=torch.uint8, device=device)
        with tqdm(
            total=n, desc="loading frames", unit="frame", disable=not progress, mininterval=1.0
        ) as bar:
            for start, stop in _runs(frame_mask):
                for a in range(start, stop, READ_BLOCK_FRAMES):
                    b = min(a + READ_BLOCK_FRAMES, stop)
                    block = resize_frames(ds.read_frames(a, b), image_size)
                    frames[compact[a] : compact[a] + (b - a)] = torch.from_numpy(
                        np.ascontiguousarray(block)
                    ).to(device, non_blocking=False)
                    bar.update(b - a)
        return cls(frames, compact)

    @staticmethod
    def nbytes(frame_mask: np.ndarray, image_size: int) -> int:
        return int(frame_mask.sum()) * image_size * image_size * 3


class DeviceWindows:
    """Device-mode windows: batches gathered from :class:`DeviceFrames` and labelled on the device.

    ``batch(index)`` with (B,) window indices returns (images (B, inputs, S, S, 3) uint8
    RGB, the rest image first if the labels have rests; targets (B, S, S) float32 kPa),
    both on the frames' device.
    """

    def __init__(self, store: DeviceFrames, labels: WindowLabels, span: int):
        device = store.frames.device
        compact_ends = store.compact[labels.ends]
        if (compact_ends < span - 1).any() or (store.compact[labels.ends - span + 1] < 0).any():
            raise ValueError("DeviceWindows: the frame store lacks frames of some windows")
        self.store = store
        self.labels = labels
        self.span = span
        self.device = device
        self._ends = torch.as_tensor(compact_ends, device=device)
        self._offsets = torch.arange(-span + 1, 1, device=device)  # oldest first
        self._force = torch.as_tensor(labels.force_n, dtype=torch.float32, device=device)
        self._position = torch.as_tensor(labels.position_mm, dtype=torch.float32, device=device)
        self._contact = torch.as_tensor(labels.contact, device=device)
        self._rests = None
        if labels.rests is not None:
            compact_rests = store.compact[labels.rests]
            if (compact_rests < REST_FRAMES - 1).any() or (
                store.compact[labels.rests - REST_FRAMES + 1] < 0
            ).any():
                raise ValueError("DeviceWindows: the frame store lacks rest frames of some windows")
            self._rests = torch.as_tensor(compact_rests, device=device)
            self._rest_offsets = torch.arange(-REST_FRAMES + 1, 1, device=device)

    def __len__(self) -> int:
        return len(self.labels)

    def batch(self, index: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        idx = index_on(self.device, index)
        rows = self._ends[idx][:, None] + self._offsets[None]  # (B, T) frame rows
        frames = self.store.frames.index_select(0, rows.reshape(-1))  # (B*T, S, S, 3)
        frames = frames.view(len(idx), self.span, *frames.shape[1:])  # (B, span, S, S, 3)
        if self._rests is not None:
            rows = self._rests[idx][:, None] + self._rest_offsets[None]  # (B, K) rest rows
            rest = self.store.frames.index_select(0, rows.reshape(-1))
            rest = rest.view(len(idx), REST_FRAMES, *rest.shape[1:]).float().mean(1)
            rest = rest.round_().to(torch.uint8)  # (B, S, S, 3): as average_rest
            frames = torch.cat([rest[:, None], frames], dim=1)  # (B, 1 + span, S, S, 3)
        targets = label_maps(
            self._force[idx], self._position[idx], self._contact[idx], self.labels.geometry
        )
        return frames, targets


# --- batching ------------------------------------------------------------------------
def epoch_batches(
    n: int,
    batch_size: int,
    *,
    epoch: int,
    seed: int,
    shuffle: bool,
    augment: bool,
    rank: int = 0,
    world_size: int = 1,
    pad: bool = True,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """This rank's batches of one epoch: [(window indices (b,), D4 indices (b,)), ...].

    Like ``DistributedSampler``: one order for all ranks (a permutation seeded by
    ``(seed, epoch)`` when ``shuffle``), padded by wrapping to a multiple of
    ``world_size`` when ``pad`` (so every rank runs the same number of batches),
    rank ``r`` taking every ``world_size``-th window from ``r``. ``batch_size`` is
    per rank. Within a batch, samples are ordered by D4 index (batch order does
    not matter to training; it lets each transform act on one slice).
    """
    rng = np.random.default_rng([seed, epoch])
    order = rng.permutation(n) if shuffle else np.arange(n)
    ks = rng.integers(0, D4_ORDER, size=n) if augment else np.zeros(n, dtype=np.int64)
    if pad and world_size > 1 and n % world_size:
        extra = world_size - n % world_size
        order = np.concatenate([order, np.resize(order, extra)])
        ks = np.concatenate([ks, np.resize(ks, extra)])
    order, ks = order[rank::world_size], ks[rank::world_size]
    batches = []
    for i in range(0, len(order), batch_size):
        b_idx, b_ks = order[i : i + batch_size], ks[i : i + batch_size]
        sort = np.argsort(b_ks, kind="stable")
        batches.append((b_idx[sort], b_ks[sort]))
    return batches


class _PlanSampler:
    """batch_sampler for a DataLoader: yields the current epoch plan's index lists."""

    def __init__(self) -> None:
        self.plan: list[tuple[np.ndarray, np.ndarray]] = []

    def __iter__(self) -> Iterator[list[int]]:
        for idx, _ in self.plan:
            yield idx.tolist()

    def __len__(self) -> int:
        return len(self.plan)


def _worker_init(_: int) -> None:
    cv2.setNumThreads(1)


class WindowLoader:
    """Batches of windows on the training device, deterministic given (seed, epoch).

    Iterating yields (frames (B, T, S, S, 3) uint8 RGB, targets (B, S, S) float32 kPa)
    on ``device``. Call :meth:`set_epoch` before each epoch (optionally skipping the
    first batches, to resume mid-epoch). ``source`` is a :class:`DeviceWindows`
    (device mode) or a :class:`WindowDataset` (host mode, read by a DataLoader with
    ``num_workers`` workers). ``stride`` keeps every stride-th window (cheaper
    validation: neighbouring windows overlap by T-1 frames).
    """

    def __init__(
        self,
        source: DeviceWindows | WindowDataset,
        batch_size: int,
        *,
        device: torch.device,
        shuffle: bool,
        augment: bool,
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        num_workers: int = 0,
        stride: int = 1,
        pad: bool = True,
    ):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.source = source
        self.batch_size = batch_size
        self.device = torch.device(device)
        self.shuffle, self.augment, self.seed = shuffle, augment, seed
        self.rank, self.world_size, self.pad = rank, world_size, pad
        self.subset = np.arange(0, len(source), max(1, stride))
        self.mode = "device" if isinstance(source, DeviceWindows) else "host"
        self._sampler = _PlanSampler()
        self._loader = None
        if self.mode == "host":
            self._loader = torch.utils.data.DataLoader(
                source,
                batch_sampler=self._sampler,
                num_workers=num_workers,
                pin_memory=self.device.type == "cuda",
                persistent_workers=num_workers > 0,
                worker_init_fn=_worker_init if num_workers > 0 else None,
                prefetch_factor=4 if num_workers > 0 else None,
                # spawn, not fork: a forked worker inherits OpenCV's thread pool and HDF5
                # state from the parent and can deadlock in them
                multiprocessing_context=WORKER_START_METHOD if num_workers > 0 else None,
                # Its own generator: each new iterator (every epoch, validation, a resume)
                # draws a worker seed from it, not from the global RNG that input noise
                # and dropout draw from, so a resumed run continues the same stream.
                generator=torch.Generator().manual_seed(seed * 1000 + rank),
            )
        self.set_epoch(0)

    @property
    def num_windows(self) -> int:
        return len(self.subset)

    def set_epoch(self, epoch: int, skip_batches: int = 0) -> None:
        plan = epoch_batches(
            len(self.subset),
            self.batch_size,
            epoch=epoch,
            seed=self.seed,
            shuffle=self.shuffle,
            augment=self.augment,
            rank=self.rank,
            world_size=self.world_size,
            pad=self.pad,
        )
        self._sampler.plan = [(self.subset[idx], ks) for idx, ks in plan[skip_batches:]]
        self._full_length = len(plan)

    def __len__(self) -> int:
        """Batches per full epoch on this rank."""
        return self._full_length

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        plan = list(self._sampler.plan)
        if self.mode == "device":
            for idx, ks in plan:
                frames, targets = self.source.batch(idx)
                yield d4_batch(frames, targets, ks)
        else:
            for (frames, targets), (_, ks) in zip(self._loader, plan, strict=True):
                frames = frames.to(self.device, non_blocking=True)
                targets = targets.to(self.device, non_blocking=True)
                yield d4_batch(frames, targets, ks)


# --- choosing a loader mode ---------------------------------------------------------
def available_memory_bytes(device: torch.device) -> int:
    """Free memory on ``device``: GPU free memory, or the host's MemAvailable."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def choose_loader_mode(mode: str, frames_bytes: int, device: torch.device, copies: int = 1) -> str:
    """Resolve ``"auto"`` to ``"device"`` when ``copies`` x ``frames_bytes`` fit in a fraction
    of the device's free memory (RAM for CPU training), else ``"host"``."""
    if mode not in LOADER_MODES:
        raise ConfigError(f"loader must be one of {LOADER_MODES}, got {mode!r}")
    if mode != "auto":
        return mode
    fraction = DEVICE_MEMORY_FRACTION if device.type == "cuda" else HOST_MEMORY_FRACTION
    budget = available_memory_bytes(device) * fraction
    chosen = "device" if frames_bytes * copies <= budget else "host"
    logger.info(
        "loader auto -> %s (frames need %.2f GB x %d, budget %.2f GB on %s)",
        chosen,
        frames_bytes / 1e9,
        copies,
        budget / 1e9,
        device,
    )
    return chosen


def batches_per_epoch(num_windows: int, batch_size: int, world_size: int = 1) -> int:
    """Optimizer steps per epoch: every window once (padded to a multiple of world_size)."""
    per_rank = math.ceil(num_windows / world_size)
    return math.ceil(per_rank / batch_size)
