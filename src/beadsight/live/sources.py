"""Cameras for live sensing: which camera a source names, and how its frames become model input.

Live sensing reads any :class:`beadsight.devices.Camera` - the same camera classes that
collection records from: :func:`open_camera` turns a ``--source`` (``"sim"``, a camera
index or device path, a dataset file to replay, a video file) into one. The camera's
reader thread keeps the frames with their capture timestamps (capture never waits for
inference); :meth:`~beadsight.devices.Camera.async_read` hands the sensor every frame since
its last read, so its temporal window stays consecutive. The camera's errors drive the sensor:
:class:`~beadsight.devices.CameraDisconnectedError` (a live camera was lost: reopen it
with backoff), :class:`~beadsight.devices.CameraEndedError` (a video, a replayed dataset
or the simulator ended), :class:`~beadsight.devices.DeviceTimeoutError` (no frame for a
while).

:func:`frame_converter` decides, from the first frame, how frames become the model's
input: (S, S, 3) uint8 RGB.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.devices.base import Camera, Frame
from beadsight.errors import BeadSightError

logger = logging.getLogger(__name__)

DEFAULT_SIM_FPS = 30.0  # the reference camera's rate


def open_camera(
    spec: int | str | os.PathLike | Camera,
    image_size: int,
    fps: float | None = None,
    loop: bool = False,
    seed: int = 0,
    any_size: bool = False,
    drift: str | None = None,
) -> Camera:
    """A (not yet connected) camera for ``spec``: a Camera (used as it is), ``"sim"``, a
    camera index (int or a string of digits) or device path, a dataset file (``.h5``,
    ``.hdf5``: its rows replayed, :class:`~beadsight.devices.replay.DatasetCamera`), or a
    video file path.

    image_size: the simulator's frame size (the model's; a replayed dataset's frames are
    resized to it). fps: the simulator's rate (default 30), a replayed dataset's (default:
    the file's), or the rate asked of a camera (a video file plays at its own rate).
    loop: restart a video or dataset (or the simulator's session) at its end. seed: the
    simulator's. any_size: accept any camera resolution (when a custom preprocessing is
    given) instead of requiring the reference camera's 1280x1024. drift: the simulator's
    drift (:func:`beadsight.sim.drift.parse_drift` text); refused for other sources.
    """
    from beadsight.devices.opencv import OpenCVCamera, is_device_path
    from beadsight.devices.replay import DatasetCamera, is_dataset_path

    if not isinstance(spec, (int, str, os.PathLike)):
        if not isinstance(spec, Camera):
            raise TypeError(
                f"source must be a camera index, a video file, 'sim' or a beadsight.devices."
                f"Camera, got {type(spec).__name__}"
            )
        return spec
    is_sim = isinstance(spec, str) and spec.strip().lower() == "sim"
    if drift is not None and not is_sim:
        raise BeadSightError(f"--sim-drift: only the simulator drifts on purpose, not {spec!r}")
    if is_sim:
        from beadsight.devices.virtual.camera import SimCamera

        return SimCamera(image_size, fps=fps or DEFAULT_SIM_FPS, seed=seed, loop=loop, drift=drift)
    text = os.fspath(spec) if isinstance(spec, os.PathLike) else spec
    if isinstance(text, int) or text.strip().isdigit() or is_device_path(text):
        # a camera: the reference mode (1280x1024 MJPG, fps or 30), any size if asked
        mode: dict[str, Any] = {"fps": fps} if fps else {}
        if any_size:
            mode.update(width=None, height=None)
        return OpenCVCamera(text, **mode)
    if is_dataset_path(text):
        return DatasetCamera(text, image_size, fps, loop=loop)
    return OpenCVCamera(
        text, width=None, height=None, realtime=True, loop=loop, name=f"video {Path(text)}"
    )


# --- frame -> model input --------------------------------------------------------------------
def frame_converter(
    first: Frame,
    source_name: str,
    image_size: int,
    preprocess: str | Path | None = "auto",
) -> Callable[[Frame], np.ndarray]:
    """How frames like ``first`` become (S, S, 3) uint8 RGB model input: the one rule of
    :func:`beadsight.inference.frames.input_converter` (``preprocess`` "auto" by default;
    None means "auto")."""
    from beadsight.inference.frames import input_converter

    convert = input_converter(
        first.image, first.channel_order, image_size, preprocess, f"source {source_name}"
    )
    return lambda frame: convert(frame.image)
