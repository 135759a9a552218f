"""Where ``beadsight predict`` takes a rest-referenced model's rest images from.

:func:`stream_rest` picks one :class:`StreamRest` for a run: a rest file
(:class:`FileRest`, the rest file of live and health,
:func:`beadsight.data.rest.load_rest_file`), else a dataset's own rest frames
(:class:`DatasetRest`, the rule of training and evaluation, :mod:`beadsight.data.rest`),
else the input's first :data:`~beadsight.data.rest.REST_FRAMES` frames
(:class:`StreamStartRest`). ``source`` names each in the output file (``rest_source``).

"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from beadsight.data.rest import REST_FRAMES, RestFileError, average_rest, load_rest_file
from beadsight.data.windows import RestImages

if TYPE_CHECKING:
    from beadsight.checkpoint import PressureModel
    from beadsight.data.dataset import Dataset

log = logging.getLogger(__name__)

REST_NONE = "none"  # rest_source: the model has no rest input
REST_FROM_FILE = "file"  # ... a rest file (--rest FILE)
REST_FROM_STREAM = "stream_start"  # ... the average of the input's first REST_FRAMES frames
REST_FROM_DATASET = "dataset"  # ... each frame's rest image by the dataset rule (data.rest)


class StreamRest:
    """Rest images of a stream of frames: ``rest(frames, start)`` with a chunk's (n, S, S, 3)
    uint8 RGB frames, the first at input index ``start`` -> (rest images (n, S, S, 3) uint8
    RGB, (n,) bool: the frame has one). Chunks come in order. ``source`` and ``note``
    describe where the images come from."""

    source = REST_NONE
    note = ""

    def __call__(self, frames: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError  # pragma: no cover - interface


class FileRest(StreamRest):
    """The rest image of a rest file (:func:`~beadsight.data.rest.load_rest_file`: the
    .npz ``live``/``health --save-rest`` write), for every frame."""

    source = REST_FROM_FILE

    def __init__(self, path: Path, image_size: int):
        self.path = path
        if not Path(path).is_file() and not Path(path).is_dir():
            raise RestFileError(f"rest file {path}: not found")
        self.image = load_rest_file(path, image_size).image
        self.note = f"the rest image of {path}, for every frame"

    def __call__(self, frames: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
        n = len(frames)
        return np.broadcast_to(self.image, (n, *self.image.shape)), np.ones(n, dtype=bool)


class StreamStartRest(StreamRest):
    """The average of the stream's first REST_FRAMES frames; the frames before the last of
    them have none."""

    source = REST_FROM_STREAM
    note = (
        f"the average of the input's first {REST_FRAMES} frames, taken as the unloaded, still "
        "pouch; the frames before its last one have no prediction"
    )

    def __init__(self) -> None:
        self._frames: list[np.ndarray] = []
        self.image: np.ndarray | None = None

    def __call__(self, frames: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
        n = len(frames)
        if self.image is None:
            self._frames.append(frames[: REST_FRAMES - start].copy())
            if start + n >= REST_FRAMES:
                self.image = average_rest(np.concatenate(self._frames))
                self._frames = []
        has = start + np.arange(n) >= REST_FRAMES - 1
        if self.image is None:
            return np.zeros_like(frames), has
        return np.broadcast_to(self.image, frames.shape), has


class DatasetRest(StreamRest):
    """Each dataset frame's own rest image (:class:`~beadsight.data.windows.RestImages`)."""

    source = REST_FROM_DATASET
    note = (
        f"each frame's rest image by the dataset rule (the average of the {REST_FRAMES} "
        "frames ending the newest settled unloaded run before it); frames without one have "
        "no prediction"
    )

    def __init__(self, ds: Dataset):
        self.rests = RestImages(ds)

    def __call__(self, frames: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
        index = start + np.arange(len(frames))
        has = self.rests.has_rest(index)
        images = np.zeros_like(frames)
        if has.any():
            images[has] = self.rests(index[has])
        return images, has


def stream_rest(
    model: PressureModel, ds: Dataset | None, rest: str | Path | None = None
) -> StreamRest:
    """The rest images of a rest-referenced ``model``'s run: from the file ``rest``, else
    from the dataset ``ds`` being read, else from the stream's first frames."""
    if rest is not None:
        chosen: StreamRest = FileRest(Path(rest), model.image_size)
    elif ds is not None:
        chosen = DatasetRest(ds)
    else:
        chosen = StreamStartRest()
    log.info("rest-referenced model: rest image from %s", chosen.note)
    return chosen
