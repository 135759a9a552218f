"""What a new sensor's model can adapt without training its weights.

* **The rest reference** (:class:`RestFrames`): the new pouch untouched, from a rest file
  (the ``.npz`` of ``live --rest``, :func:`beadsight.data.rest.load_rest_file`) or from
  the frames of a dataset's presses before each makes contact
  (:func:`pre_contact_mask`). Its rest image (the dataset rule of
  :mod:`beadsight.data.rest`) is written beside a calibration as ``rest.npz``.
* **Zero-press alignment** (:func:`align_to_rest`): the normalisation statistics (per
  channel mean and std, 0..255) become those of the rest frames. This matches the
  brightness, contrast and colour balance of the new camera and lights to what the
  network saw in training. A model without rest input cannot take a per-pixel rest
  reference; a rest-referenced one gets each window's own rest image from the data, as
  in training and evaluation (:mod:`beadsight.data.windows`), and is aligned as well.
* **Force gain** (:func:`fit_force_gain`): one factor on the output scale, the least
  squares fit of the predicted to the measured total force on training frames in
  contact (a pouch stiffer or softer than the base model's).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.data.dataset import Dataset, DatasetError, open_dataset
from beadsight.data.rest import REST_FRAMES, RestFileError, average_rest, load_rest_file, rest_ends
from beadsight.data.splits import dataset_window_ends
from beadsight.data.windows import WindowReader, pixel_stats, resize_frames
from beadsight.geometry import total_force_n

logger = logging.getLogger(__name__)

MIN_REST_FRAMES = 10  # fewer rest frames than this cannot measure the statistics
GAIN_MAX_FRAMES = 512  # contact frames predicted to fit the force gain
GAIN_RANGE = (0.2, 5.0)  # a fitted gain outside this means a broken fit, not a pouch
BATCH = 32


def pre_contact_mask(ds: Dataset, press_ids: np.ndarray) -> np.ndarray:
    """(N,) bool: valid frames of the presses ``press_ids`` before each makes contact."""
    index = np.arange(len(ds))
    cycle = ds.press_id
    start = np.full(len(ds), -1, dtype=np.int64)
    inside = cycle >= 0
    start[inside] = ds.presses[cycle[inside], 0]
    return ds.valid & inside & (index < start) & np.isin(cycle, press_ids) & ~ds.contact


def with_meta(model: PressureModel, **changes) -> PressureModel:
    """A copy of ``model`` (same weights, same device) with metadata fields changed."""
    new = PressureModel.create(dataclasses.replace(model.meta, **changes))
    new.module.net.load_state_dict(model.module.net.state_dict())
    return new.to(model.device)


@dataclass(frozen=True)
class RestFrames:
    """The new pouch at rest: ``mean``/``std`` per RGB channel (0..255) of its rest frames,
    its rest ``image`` ((S, S, 3) uint8 RGB at the model's size; None where the data has
    no settled rest) and ``record`` (what metrics.json says: source, frames, count)."""

    mean: list[float]
    std: list[float]
    image: np.ndarray | None
    record: dict


def rest_from_file(path: str, image_size: int) -> RestFrames:
    """The rest file ``path`` (.npz, :func:`~beadsight.data.rest.load_rest_file`) at the
    model's ``image_size``. Its statistics are those of its one image, the average of
    ``frames`` still frames (so without the camera noise of single frames)."""
    if not Path(path).exists():
        raise RestFileError(f"rest file {path}: not found; expected a rest file (.npz)")
    ref = load_rest_file(path, image_size)
    pixels = ref.image.reshape(-1, 3).astype(np.float64)
    mean, std = pixels.mean(0), np.maximum(pixels.std(0), 1e-3)
    what = f"the rest file's image (the average of {ref.frames} frames)"
    record = {"source": str(path), "frames": what, "count": ref.frames}
    return RestFrames(mean.tolist(), std.tolist(), ref.image, record)


def rest_from_data(data: str, press_ids: np.ndarray, image_size: int) -> RestFrames:
    """The rest frames of dataset ``data``: the valid frames of presses ``press_ids``
    before each makes contact (the statistics), and the newest rest image of the dataset
    rule (:func:`~beadsight.data.rest.rest_ends`) at ``image_size``."""
    with open_dataset(data) as ds:
        mask = pre_contact_mask(ds, press_ids)
        what = "pre-contact frames of the presses"
        count = int(mask.sum())
        if count < MIN_REST_FRAMES:
            raise DatasetError(
                f"{ds.path}: {count} rest frames ({what}); the zero-press alignment "
                f"needs at least {MIN_REST_FRAMES} frames of the untouched sensor"
            )
        mean, std = pixel_stats(ds, mask, image_size)
        newest = int(rest_ends(ds.force_n, ds.valid)[-1])
        image = None
        if newest >= 0:
            frames = ds.read_frames(newest - REST_FRAMES + 1, newest + 1)
            image = average_rest(resize_frames(frames, image_size))
    record = {"source": str(data), "frames": what, "count": count, "rest_image_end": newest}
    return RestFrames(list(mean), list(std), image, record)


def align_to_rest(model: PressureModel, rest: RestFrames) -> tuple[PressureModel, dict]:
    """``model`` with the normalisation of the new sensor's rest frames ``rest``."""
    mean, std = list(rest.mean), list(rest.std)
    if model.meta.channel_order == "BGR":
        mean, std = mean[::-1], std[::-1]
    record = {
        **rest.record,
        "pixel_mean_before": [float(v) for v in model.meta.pixel_mean],
        "pixel_std_before": [float(v) for v in model.meta.pixel_std],
        "pixel_mean": [float(v) for v in mean],
        "pixel_std": [float(v) for v in std],
        "channel_order": model.meta.channel_order,
    }
    logger.info(
        "alignment: %d rest frames (%s): pixel mean %s -> %s",
        record["count"],
        record["frames"],
        np.round(record["pixel_mean_before"], 1).tolist(),
        np.round(mean, 1).tolist(),
    )
    return with_meta(model, pixel_mean=mean, pixel_std=std), record


def fit_force_gain(
    model: PressureModel, data: str, train_ids: np.ndarray, max_frames: int = GAIN_MAX_FRAMES
) -> float:
    """The factor g minimising sum (g * F_pred - F_true)^2 over (up to ``max_frames``,
    evenly spaced) training frames in contact; F = total force of the map, N. A
    rest-referenced model's frames are those with a rest image before them."""
    rest = bool(model.rest)
    with open_dataset(data) as ds:
        ends = dataset_window_ends(ds, model.span, train_ids, rest=rest)
        ends = ends[ds.contact[ends]]
        if ends.size == 0:
            raise DatasetError(f"{ds.path}: no training frame in contact to fit a force gain on")
        ends = ends[
            np.unique(np.linspace(0, ends.size - 1, min(ends.size, max(max_frames, 1))).astype(int))
        ]
        reader = WindowReader(ds, model.span, model.image_size, rest)
        geometry = ds.geometry.with_image_size(model.image_size)
        pred = np.concatenate(
            [
                total_force_n(model.predict(reader(ends[i : i + BATCH]), BATCH), geometry)
                for i in range(0, ends.size, BATCH)
            ]
        )
        true = ds.force_n[ends]
    denominator = float(np.dot(pred, pred))
    if not denominator > 0:
        logger.warning("force gain: the model predicts no force on the training presses; gain 1")
        return 1.0
    gain = float(np.dot(pred, true) / denominator)
    clipped = float(np.clip(gain, *GAIN_RANGE))
    if clipped != gain:
        logger.warning("force gain %.3f outside %s: using %.3f", gain, GAIN_RANGE, clipped)
    return clipped
