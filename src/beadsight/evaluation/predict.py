"""Run a pressure model over a whole recording (a dataset or a video file).

:func:`predict_recording` streams frames through a ring buffer of the model's
window (memory does not grow with the recording's length), predicts in batches
and appends the results to an HDF5 file written under a temporary name and
renamed into place at the end, so an interrupted run never leaves a truncated
file where a finished one is expected. A write that fails (disk full) raises
:class:`beadsight.files.WriteError` naming the file; the partial file is removed.

Output layout (``format = "beadsight-predictions"``), one row per input frame:

=================  ===========  =======  ===============================================
dataset            shape        dtype    content
=================  ===========  =======  ===============================================
``pressure_kpa``   (N, S, S)    float32  predicted pressure, kPa (gzip); zeros where
                                         ``valid`` is False
``force_n``        (N,)         float64  total force (integral of the map), N
``cop_mm``         (N, 2)       float64  centre of pressure (x, y) mm, printer frame;
                                         NaN exactly where ``has_pressure`` is False
``has_pressure``   (N,)         bool     the map has some positive pressure
``timestamp_s``    (N,)         float64  dataset timestamps (unix s), or video frame
                                         times (s from the start of the video)
``frame_index``    (N,)         int64    index of the frame in the input
``valid``          (N,)         bool     False for the first span-1 frames (no full window)
                                         and, for a rest-referenced model, for frames
                                         without a rest image
=================  ===========  =======  ===============================================

Attributes include ``frames`` (T, the frames the network sees) and ``span`` (the
frames one window covers); files of format version 1 have ``window`` (the span)
instead of both. ``rest_source`` says where a rest-referenced model's rest image came
from (``rest_note`` in words):

* ``"file"``: ``--rest FILE``
  (:func:`~beadsight.data.rest.load_rest_file`; ``rest_file`` names it),
  for every frame;
* ``"stream_start"`` (videos without ``--rest``): the average of the input's first
  :data:`~beadsight.data.rest.REST_FRAMES` frames, taken as the unloaded, still pouch;
  the frames before its last one have no prediction;
* ``"dataset"`` (datasets without ``--rest``): each frame's own rest image by the rule of
  training and evaluation (:mod:`beadsight.data.rest`); frames with no unloaded, settled
  run before them have no prediction;
* ``"none"``: the model has no rest input.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm import tqdm

from beadsight import __version__
from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.data.dataset import open_dataset
from beadsight.data.windows import WindowBuffer
from beadsight.errors import BeadSightError
from beadsight.evaluation.config import (
    DEFAULT_BACKEND,
    DEFAULT_DEVICE,
    PREDICT_PREPROCESS,
    check_runtime,
)
from beadsight.evaluation.config import PREDICT_BATCH_SIZE as DEFAULT_BATCH_SIZE
from beadsight.evaluation.h5writer import IncrementalH5
from beadsight.evaluation.rest_images import REST_NONE, FileRest, StreamRest, stream_rest
from beadsight.files import refuse_existing
from beadsight.geometry import centre_of_pressure_mm, total_force_n
from beadsight.inference.backend import Backend
from beadsight.inference.frames import check_preprocess, input_converter
from beadsight.inference.select import create_backend
from beadsight.preprocess import FrameSizeError
from beadsight.torch_device import resolve_device

log = logging.getLogger(__name__)

PREDICTIONS_FORMAT = "beadsight-predictions"
PREDICTIONS_FORMAT_VERSION = 2  # 2: attributes "frames" and "span" replace "window"
READ_CHUNK_FRAMES = 64  # frames read from a dataset at a time


class PredictionError(BeadSightError):
    """The input recording cannot be run through the model; the message says why."""


# --- devices ------------------------------------------------------------------------
def as_model(checkpoint: PressureModel | str | Path, device: str | torch.device) -> PressureModel:
    """A loaded model on ``device`` (:func:`beadsight.torch_device.resolve_device`): a
    PressureModel is moved, a path is loaded."""
    model = checkpoint if isinstance(checkpoint, PressureModel) else load_checkpoint(checkpoint)
    return model.to(resolve_device(device, "--device"))


@contextmanager
def open_runtime(
    model: PressureModel, backend: str = DEFAULT_BACKEND, precision: str = "auto"
) -> Iterator[Backend]:
    """The runtime of live sensing (:func:`beadsight.inference.select.create_backend`)
    that runs ``model`` offline, closed on exit. ``backend``: "torch" (on the model's
    device), "onnx", "openvino", "int8", ... or "auto". It is built without a parity
    check: evaluating it is the check (``metrics.json`` names it)."""
    check_runtime(backend, precision)
    device = model.device if backend == "torch" or model.device.type == "cuda" else None
    runtime = create_backend(model, backend, precision, device=device, check=False)
    try:
        yield runtime
    finally:
        runtime.close()


# --- frame sources ------------------------------------------------------------------
@dataclass
class _Chunk:
    frames: np.ndarray  # (n, S, S, 3) uint8 RGB at the model's size
    timestamp_s: np.ndarray  # (n,) float64


class _Source:
    kind = ""
    total: int | None = None
    preprocess = "none"
    fps = float("nan")

    def chunks(self, size: int) -> Iterator[_Chunk]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


class _DatasetSource(_Source):
    kind = "dataset"

    def __init__(self, path: Path, model: PressureModel, preprocess: str):
        if preprocess not in ("auto", "none"):
            raise PredictionError(
                f"{path}: --preprocess {preprocess} applies to raw camera video; dataset frames "
                "are already preprocessed (use auto or none)"
            )
        self.ds = open_dataset(path)
        if self.ds.image_size != model.image_size:
            size = self.ds.image_size
            self.ds.close()
            raise PredictionError(
                f"{path}: dataset frames are {size}x{size} px, but the checkpoint "
                f"{model.source} expects image_size={model.image_size}x{model.image_size}"
            )
        self.total = len(self.ds)
        self.fps = self.ds.fps

    def chunks(self, size: int) -> Iterator[_Chunk]:
        for i in range(0, len(self.ds), size):
            j = min(i + size, len(self.ds))
            yield _Chunk(self.ds.read_frames(i, j), self.ds.timestamp_s[i:j])

    def close(self) -> None:
        self.ds.close()


class _VideoSource(_Source):
    kind = "video"

    def __init__(self, path: Path, model: PressureModel, preprocess: str):
        import cv2

        self.path = path
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise PredictionError(
                f"{path}: not a readable video or HDF5 dataset (OpenCV cannot open it)"
            )
        ok, first = self.cap.read()
        if not ok or first is None:
            self.cap.release()
            raise PredictionError(f"{path}: the video has no readable frames")
        self._first = first
        count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.total = count if count > 0 else None
        fps = float(self.cap.get(cv2.CAP_PROP_FPS))
        self.fps = fps if fps > 0 else float("nan")
        self._convert = self._converter(first, model, preprocess)
        self.preprocess = self._convert.mode

    def _converter(self, first: np.ndarray, model: PressureModel, preprocess: str):
        try:
            return input_converter(first, "BGR", model.image_size, preprocess, str(self.path))
        except FrameSizeError as e:
            self.cap.release()
            raise PredictionError(f"{e} (checkpoint {model.source})") from None

    def _frame(self, bgr: np.ndarray, index: int) -> np.ndarray:
        if bgr.shape != self._first.shape:
            raise PredictionError(
                f"{self.path}: frame {index} is {bgr.shape}, but the video started with "
                f"{self._first.shape} frames"
            )
        return np.asarray(self._convert(bgr), dtype=np.uint8)

    def chunks(self, size: int) -> Iterator[_Chunk]:
        import cv2

        index = 0
        pending = self._first
        while pending is not None:
            frames, times = [], []
            while pending is not None and len(frames) < size:
                if np.isfinite(self.fps):
                    times.append(index / self.fps)
                else:
                    times.append(self.cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
                frames.append(self._frame(pending, index))
                index += 1
                ok, nxt = self.cap.read()
                pending = nxt if ok else None
            yield _Chunk(np.stack(frames), np.asarray(times, np.float64))

    def close(self) -> None:
        self.cap.release()


def _open_source(path: Path, model: PressureModel, preprocess: str) -> _Source:
    try:
        preprocess = check_preprocess(preprocess or "")
    except ValueError as e:
        raise PredictionError(f"--{e}") from None
    if not path.is_file():
        raise PredictionError(f"{path}: input file not found")
    if h5py.is_hdf5(path):
        return _DatasetSource(path, model, preprocess)
    return _VideoSource(path, model, preprocess)


# --- prediction ---------------------------------------------------------------------
def _output_specs(s: int) -> dict[str, tuple[tuple[int, ...], object, bool]]:
    return {
        "pressure_kpa": ((s, s), np.float32, True),
        "force_n": ((), np.float64, False),
        "cop_mm": ((2,), np.float64, False),
        "has_pressure": ((), bool, False),
        "timestamp_s": ((), np.float64, False),
        "frame_index": ((), np.int64, False),
        "valid": ((), bool, False),
    }


def _summaries(maps: np.ndarray, model: PressureModel) -> dict[str, np.ndarray]:
    force = np.asarray(total_force_n(maps.astype(np.float64), model.geometry))
    has = np.clip(maps, 0, None).sum(axis=(1, 2)) > 0
    return {
        "force_n": force,
        "cop_mm": centre_of_pressure_mm(maps, model.geometry),
        "has_pressure": has,
    }


def predict_recording(
    checkpoint: PressureModel | str | Path,
    input: str | Path,
    out: str | Path,
    *,
    preprocess: str = PREDICT_PREPROCESS,
    batch_size: int = DEFAULT_BATCH_SIZE,
    device: str | torch.device = DEFAULT_DEVICE,
    progress: bool = True,
    rest: str | Path | None = None,
    overwrite: bool = False,
    backend: str = DEFAULT_BACKEND,
    precision: str = "auto",
) -> Path:
    """Predict a pressure map for every frame of a dataset or video; write ``out`` (HDF5).

    checkpoint: a PressureModel or a checkpoint path. input: a beadsight/reference
    HDF5 dataset (frames at the model's size) or a video file readable by OpenCV.
    preprocess: how video frames become model input, the rule of
    :mod:`beadsight.inference.frames` ("auto": frames at the model's size as they are,
    raw 1280x1024 camera frames through the reference pipeline, other sizes refused;
    "none", "reference", "reference-linear", or a fisheye lens .json). Dataset
    frames are already preprocessed ("auto" or "none").
    rest: for a rest-referenced model, a rest file
    (:func:`~beadsight.data.rest.load_rest_file`); without it
    the rest image comes from the input (``rest_source`` in this module's docstring).
    An existing ``out`` is refused unless ``overwrite``.
    backend, precision: the runtime (:func:`open_runtime`; attribute ``backend``).
    Returns the output path; the layout is in this module's docstring.
    """
    if batch_size < 1:
        raise PredictionError(f"--batch-size must be >= 1, got {batch_size}")
    input, out = Path(input), Path(out)
    if not input.is_file():
        raise PredictionError(f"{input}: input file not found")
    if out.exists() and out.resolve() == input.resolve():
        raise PredictionError(f"{out}: the output would overwrite the input")
    refuse_existing(out, overwrite)
    model = as_model(checkpoint, device)
    check_runtime(backend, precision)
    source = _open_source(input, model, preprocess)
    s, t = model.image_size, model.span
    valid = 0
    try:
        if rest is not None and not model.rest:
            raise PredictionError(
                f"--rest {rest}: the checkpoint {model.source} is not rest-referenced (it "
                "takes no rest image); leave --rest out"
            )
        ds = source.ds if isinstance(source, _DatasetSource) else None
        rests = stream_rest(model, ds, rest) if model.rest else None
        with (
            open_runtime(model, backend, precision) as runtime,
            IncrementalH5(out, _output_specs(s)) as writer,
        ):
            writer.file.attrs.update(_attrs(model, input, source, rests))
            writer.file.attrs["backend"] = runtime.describe()
            ring = WindowBuffer(t)
            with tqdm(
                total=source.total, unit="frame", desc="predict", disable=not progress
            ) as bar:
                for chunk in source.chunks(max(batch_size, READ_CHUNK_FRAMES)):
                    valid += _predict_chunk(runtime, model, ring, rests, chunk, writer, batch_size)
                    bar.update(len(chunk.frames))
            if writer.rows < t:
                log.warning(
                    "%s: %d frames, fewer than the span of %d: no valid prediction",
                    input,
                    writer.rows,
                    t,
                )
            elif valid == 0:
                log.warning("%s: no frame has a rest image (%s)", input, rests.note)
    finally:
        source.close()
    log.info("wrote %s (%d frames)", out, writer.rows)
    return out


def _predict_chunk(
    runtime: Backend,
    model: PressureModel,
    ring: WindowBuffer,
    rests: StreamRest | None,
    chunk: _Chunk,
    writer: IncrementalH5,
    batch_size: int,
) -> int:
    """Predict and append one chunk; returns how many of its frames have a prediction."""
    n, s = len(chunk.frames), model.image_size
    if chunk.frames.shape[1:] != (s, s, 3):
        raise PredictionError(
            f"frames are {chunk.frames.shape[1:3]} px after preprocessing; the checkpoint "
            f"{model.source} expects image_size={s}x{s}"
        )
    start = writer.rows
    windows, first = ring.push(chunk.frames)  # windows end at frames first .. n-1
    valid = np.arange(n) >= first
    inputs = windows
    if rests is not None:
        images, has = rests(chunk.frames, start)
        valid &= has
        keep = has[first:]
        inputs = np.concatenate([images[first:][keep][:, None], windows[keep]], axis=1)
    maps = np.zeros((n, s, s), np.float32)
    if len(inputs):
        maps[valid] = runtime.run_batch(np.ascontiguousarray(inputs), batch_size)
    writer.append(
        pressure_kpa=maps,
        timestamp_s=chunk.timestamp_s,
        frame_index=np.arange(start, start + n, dtype=np.int64),
        valid=valid,
        **_summaries(maps, model),
    )
    return int(valid.sum())


def _attrs(model: PressureModel, input: Path, source: _Source, rests: StreamRest | None) -> dict:
    extra = {"rest_file": str(rests.path)} if isinstance(rests, FileRest) else {}
    return {
        **extra,
        "rest_source": REST_NONE if rests is None else rests.source,
        "rest_note": "" if rests is None else rests.note,
        "format": PREDICTIONS_FORMAT,
        "format_version": PREDICTIONS_FORMAT_VERSION,
        "checkpoint": str(model.source),
        "input": str(input),
        "input_kind": source.kind,
        "preprocess": source.preprocess,
        "fps": source.fps,
        "frames": model.frames,
        "span": model.span,
        "image_size": model.image_size,
        "geometry": model.geometry.to_json(),
        "units": json.dumps(
            {
                "pressure_kpa": "kPa",
                "force_n": "N",
                "cop_mm": "mm (x, y), printer frame",
                "timestamp_s": "s (dataset: unix time; video: from the start of the video)",
            }
        ),
        "cop_note": "cop_mm is NaN exactly where has_pressure is False (no positive pressure)",
        "created_unix": time.time(),
        "beadsight_version": __version__,
    }


def summarize_predictions(path: str | Path) -> str:
    """One line describing a predictions file: frames, valid frames, peak force, input."""
    path = Path(path)
    with h5py.File(path, "r") as f:
        valid = f["valid"][()]
        force = f["force_n"][()]
        rest_source = str(f.attrs.get("rest_source", REST_NONE))
        rest = "" if rest_source == REST_NONE else f" and a rest image: {rest_source}"
        peak = float(force[valid].max()) if valid.any() else float("nan")
        return (
            f"wrote {path}: {len(valid)} frames ({int(valid.sum())} with a full window"
            f"{rest}), peak force {peak:.2f} N, from {f.attrs['input_kind']} "
            f"{f.attrs['input']} (preprocess: {f.attrs['preprocess']})"
        )
