"""What a new sensor's model can adapt without training its weights.

* **Zero-press alignment** (:func:`align_to_rest`): the normalisation statistics (per
  channel mean and std, 0..255) become those of the new sensor's rest frames - a few
  seconds of the untouched sensor, or the approach frames before each press makes
  contact (:func:`pre_contact_mask`). This matches the brightness, contrast and colour
  balance of the new camera and lights to what the network saw in training. A model
  without rest input cannot take a per-pixel rest reference; a rest-referenced one gets
  each window's own rest image from the data, as in training and evaluation
  (:mod:`beadsight.data.windows`), and is aligned as well.
* **Force gain** (:func:`fit_force_gain`): one factor on the output scale, the least
  squares fit of the predicted to the measured total force on training frames in
  contact (a pouch stiffer or softer than the base model's).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.data.dataset import Dataset, DatasetError, open_dataset
from beadsight.data.splits import dataset_window_ends
from beadsight.data.windows import WindowReader, pixel_stats
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


def rest_file_mask(ds: Dataset) -> np.ndarray:
    """(N,) bool: the valid frames out of contact of a rest recording."""
    return ds.valid & ~ds.contact


def with_meta(model: PressureModel, **changes) -> PressureModel:
    """A copy of ``model`` (same weights, same device) with metadata fields changed."""
    new = PressureModel.create(dataclasses.replace(model.meta, **changes))
    new.module.net.load_state_dict(model.module.net.state_dict())
    return new.to(model.device)


def rest_statistics(ds: Dataset, mask: np.ndarray, image_size: int, what: str):
    """Per-channel RGB mean and std (0..255) of the rest frames ``mask`` at ``image_size``."""
    if int(mask.sum()) < MIN_REST_FRAMES:
        raise DatasetError(
            f"{ds.path}: {int(mask.sum())} rest frames ({what}); the zero-press alignment "
            f"needs at least {MIN_REST_FRAMES} frames of the untouched sensor"
        )
    return pixel_stats(ds, mask, image_size)


def align_to_rest(
    model: PressureModel, data: str, rest: str | None, train_ids: np.ndarray
) -> tuple[PressureModel, dict]:
    """``model`` with the normalisation of the new sensor's rest frames: those of the
    file ``rest``, else the pre-contact frames of the presses ``train_ids`` of ``data``."""
    source = rest or data
    with open_dataset(source) as ds:
        if rest:
            mask, what = rest_file_mask(ds), "valid frames out of contact"
        else:
            mask, what = pre_contact_mask(ds, train_ids), "pre-contact frames of training presses"
        mean, std = rest_statistics(ds, mask, model.image_size, what)
    if model.meta.channel_order == "BGR":
        mean, std = mean[::-1], std[::-1]
    record = {
        "source": str(source),
        "frames": what,
        "count": int(mask.sum()),
        "pixel_mean_before": [float(v) for v in model.meta.pixel_mean],
        "pixel_std_before": [float(v) for v in model.meta.pixel_std],
        "pixel_mean": [float(v) for v in mean],
        "pixel_std": [float(v) for v in std],
        "channel_order": model.meta.channel_order,
    }
    logger.info(
        "alignment: %d rest frames (%s): pixel mean %s -> %s",
        record["count"],
        what,
        np.round(record["pixel_mean_before"], 1).tolist(),
        np.round(mean, 1).tolist(),
    )
    return with_meta(model, pixel_mean=list(mean), pixel_std=list(std)), record


def fit_force_gain(model: PressureModel, data: str, train_ids: np.ndarray) -> float:
    """The factor g minimising sum (g * F_pred - F_true)^2 over (up to GAIN_MAX_FRAMES,
    evenly spaced) training frames in contact; F = total force of the map, N. A
    rest-referenced model's frames are those with a rest image before them."""
    rest = bool(model.rest)
    with open_dataset(data) as ds:
        ends = dataset_window_ends(ds, model.span, train_ids, rest=rest)
        ends = ends[ds.contact[ends]]
        if ends.size == 0:
            raise DatasetError(f"{ds.path}: no training frame in contact to fit a force gain on")
        ends = ends[
            np.unique(np.linspace(0, ends.size - 1, min(ends.size, GAIN_MAX_FRAMES)).astype(int))
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
