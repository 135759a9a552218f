"""Deprecated: the live-only frame sources of beadsight 0.2; they go away in 0.3.

Live sensing now reads :class:`beadsight.devices.Camera` objects, the same camera
classes collection uses. What replaces each name here:

==========================  ===============================================================
``FrameSource``             any :class:`~beadsight.devices.Camera`; a subclass written for
                            0.2 (``open`` / ``read_new`` / ``close``) still works: this
                            class adapts it to the camera interface.
``SourceFrame``             :class:`beadsight.devices.Frame` (``timestamp_s`` = ``t_unix``)
``PacedSource``             :class:`beadsight.devices.virtual.PlaybackCamera`
``SimSource``               :class:`beadsight.devices.virtual.SimCamera`
``CameraSource``            the camera itself
``open_source``             :func:`beadsight.live.sources.open_camera`
``SourceDisconnected``      :class:`~beadsight.devices.CameraDisconnectedError`
``SourceEnded``             :class:`~beadsight.devices.CameraEndedError`
==========================  ===============================================================
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from beadsight.devices.base import (
    Camera,
    CameraDisconnectedError,
    CameraEndedError,
    DeviceTimeoutError,
    Frame,
)
from beadsight.errors import BeadSightError

DEFAULT_TIMEOUT_S = 2.0  # a legacy source's reads wait this long when no timeout is given

REPLACED_BY = {
    "FrameSource": "beadsight.devices.Camera",
    "SourceFrame": "beadsight.devices.Frame",
    "PacedSource": "beadsight.devices.virtual.PlaybackCamera",
    "SimSource": "beadsight.devices.virtual.SimCamera",
    "CameraSource": "the camera itself (a beadsight.devices.Camera)",
    "open_source": "beadsight.live.sources.open_camera",
    "SourceDisconnected": "beadsight.devices.CameraDisconnectedError",
    "SourceEnded": "beadsight.devices.CameraEndedError",
}


class SourceDisconnected(BeadSightError):
    """The source stopped delivering frames but may come back (camera unplugged)."""


class SourceEnded(Exception):
    """A finite source (video file, finite iterator) has delivered its last frame."""


@dataclass(frozen=True)
class SourceFrame:
    """One frame from a 0.2 source: image, unix capture time, index, order, true force."""

    image: np.ndarray
    timestamp_s: float
    index: int
    channel_order: str = "BGR"
    reference_force_n: float = math.nan

    def as_frame(self) -> Frame:
        t_mono = time.monotonic() - (time.time() - self.timestamp_s)
        return Frame(
            self.image,
            self.index,
            t_mono,
            self.timestamp_s,
            self.channel_order,
            self.reference_force_n,
        )


class FrameSource(ABC):
    """A 0.2 frame source; implement ``open`` / ``read_new`` / ``close`` and it is a Camera.

    ``read_new(after_index, timeout_s, limit)`` returns the frames with ``index >
    after_index`` (at most the ``limit`` newest), ``[]`` on timeout, and raises
    :class:`SourceDisconnected` / :class:`SourceEnded`. A source reopened after a
    disconnection may start its indices again at 0.
    """

    name: str = "source"
    width = 0
    height = 0
    fps = 0.0

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def read_new(self, after_index: int, timeout_s: float, limit: int = 1) -> list[SourceFrame]: ...

    @abstractmethod
    def close(self) -> None: ...

    def read_newest(self, after_index: int, timeout_s: float) -> SourceFrame | None:
        frames = self.read_new(after_index, timeout_s, 1)
        return frames[-1] if frames else None

    # --- the Camera interface on top of the 0.2 one ----------------------------------------
    def connect(self) -> None:
        self._after_index = -1
        try:
            self.open()
        except SourceDisconnected as e:
            raise CameraDisconnectedError(self.name, str(e)) from e

    def async_read(
        self, timeout_s: float | None = None, max_frames: int | None = None
    ) -> list[Frame]:
        wait_s = DEFAULT_TIMEOUT_S if timeout_s is None else timeout_s
        try:
            frames = self.read_new(getattr(self, "_after_index", -1), wait_s, max_frames or 1 << 30)
        except SourceDisconnected as e:
            raise CameraDisconnectedError(self.name, str(e)) from e
        except SourceEnded as e:
            raise CameraEndedError(self.name, str(e) or "ended") from e
        if not frames:
            raise DeviceTimeoutError(self.name, f"no new frame within {wait_s:g} s")
        self._after_index = frames[-1].index
        return [f.as_frame() for f in frames]

    def read(self, timeout_s: float | None = None) -> Frame:
        """The next new frame (a 0.2 source may skip frames: it keeps only the newest)."""
        return self.async_read(timeout_s, 1)[-1]

    read_latest = read

    def __enter__(self) -> FrameSource:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def PacedSource(  # noqa: N802 - the 0.2 class name
    name: str,
    make_frames: Callable[[], Iterable[tuple[np.ndarray, float]]],
    fps: float,
    channel_order: str = "RGB",
    loop: bool = False,
) -> Camera:
    """Deprecated: :class:`beadsight.devices.virtual.PlaybackCamera`."""
    from beadsight.devices.virtual.camera import PlaybackCamera

    return PlaybackCamera(make_frames, fps, channel_order=channel_order, loop=loop, name=name)


def SimSource(  # noqa: N802 - the 0.2 class name
    image_size: int, fps: float | None = None, seed: int = 0, config: Any = None
) -> Camera:
    """Deprecated: :class:`beadsight.devices.virtual.SimCamera`."""
    from beadsight.devices.virtual.camera import SimCamera

    return SimCamera(image_size, fps=fps, seed=seed, config=config)


def CameraSource(  # noqa: N802 - the 0.2 class name
    name: str, make_camera: Callable[[], Camera], is_file: bool = False, loop: bool = False
) -> Camera:
    """Deprecated: use the camera itself (a video file loops with ``OpenCVCamera(loop=True)``)."""
    camera = make_camera()
    if loop and hasattr(camera, "loop"):
        camera.loop = True
    return camera


def open_source(spec: Any, image_size: int, **options: Any) -> Camera:
    """Deprecated: :func:`beadsight.live.sources.open_camera`."""
    from beadsight.live.sources import open_camera

    return open_camera(spec, image_size, **options)
