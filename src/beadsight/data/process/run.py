"""Raw recording -> dataset: clock alignment, per-frame labels, preprocessing, QA summary.

:func:`process_recording` reads a raw session of either format
(:mod:`beadsight.data.recording`) and writes a dataset
(:class:`beadsight.data.dataset_writer.DatasetWriter`, which also segments presses):

* **Labels** (:mod:`beadsight.data.process.frame_labels`): force interpolated at each frame time,
  never extrapolated; position held from the last executed printer command;
  every invalid frame gets one reason. Dataset timestamps are unix seconds.
* **Images** (:mod:`beadsight.data.process.images`): streamed chunk by chunk through a
  :class:`~beadsight.preprocess.Preprocessor` on a thread pool, so memory stays
  bounded whatever the recording length.
* **QA** (:mod:`beadsight.data.process.qa`): ``<dataset>.qa.json`` (presses, dropped frames,
  force range, invalid frames and why) and ``<dataset>.qa.png`` (press coverage map).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.plausibility import check_recording
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.frame_labels import (
    REASONS,
    FrameLabels,
    frame_labels,
    hold_positions,
    interpolate_force,
)
from beadsight.data.process.images import choose_decode, input_hw, stream_frames
from beadsight.data.process.qa import plot_qa, qa_paths, quality_summary, write_qa
from beadsight.data.recording import Recording, RecordingError, open_recording
from beadsight.errors import BeadSightError
from beadsight.files import OutputExistsError, WriteError, partial_path, refuse_existing
from beadsight.preprocess import Preprocessor

__all__ = [
    "REASONS",
    "FrameLabels",
    "frame_labels",
    "hold_positions",
    "interpolate_force",
    "plot_qa",
    "process_recording",
    "qa_paths",
    "quality_summary",
    "write_qa",
]


def process_recording(
    raw: str | Path,
    out: str | Path,
    config: ProcessConfig = ProcessConfig(),
    *,
    geometry: SensorGeometry | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Process raw session ``raw`` into dataset ``out`` (HDF5); returns the QA summary.

    Also writes ``<out>.qa.json`` and ``<out>.qa.png`` next to the dataset. An
    existing ``out`` is refused unless ``overwrite``, and a file of the recording
    itself always. The recording is checked (:mod:`beadsight.data.plausibility`)
    before anything is written; the dataset is renamed to ``out`` only once complete.
    """
    started = time.perf_counter()
    raw, out = Path(raw), Path(out)
    _check_output(raw, out, overwrite)
    rec = open_recording(raw, force_counter=config.force_counter)
    if len(rec.frames) == 0:
        raise RecordingError(f"{raw}: the frame log is empty; nothing to process")
    if not rec.videos:
        raise RecordingError(f"{raw}: no video files found")
    checked = check_recording(rec, config.scale_capacity_n)
    geometry = (geometry or _recording_geometry(rec)).with_image_size(config.image_size)
    labels = frame_labels(rec, config, checked.over_capacity)
    pre = Preprocessor.from_spec(
        config.preprocess,
        input_hw(rec),
        config.image_size,
        interpolation=config.interpolation,
        resize=config.resize,
    )
    decode = choose_decode(rec, pre, config)
    _, factor, pre_used = decode
    provenance = {
        "source": "beadsight process",
        "raw": str(raw),
        "raw_format": rec.format,
        "centre_xy_mm": list(rec.centre_xy_mm),
        "process": config.to_dict(),
        "preprocess": pre_used.to_dict(),
        "decode_scale": factor,
        "clock": labels.clock,
    }
    order = np.lexsort((rec.frames.index, rec.frames.chunk))
    stats = {"missing_video": 0, "unlogged_video": 0, "undecodable": 0}
    with (
        _no_partial_after_input_error(out),
        DatasetWriter(
            out,
            geometry,
            channel_order=pre_used.channel_order,
            fps=rec.fps,
            provenance=provenance,
            compression=config.compression,
        ) as writer,
    ):
        written = stream_frames(rec, order, labels, decode, writer, config, stats, progress)
    elapsed = time.perf_counter() - started
    qa = quality_summary(rec, labels, out, stats, written, elapsed, pre_used, factor, config)
    qa.update(force_counter=rec.force_counter, plausibility=checked.summary())
    write_qa(out, qa)
    return qa


@contextmanager
def _no_partial_after_input_error(out: Path) -> Iterator[None]:
    """Remove ``out``'s ``.partial`` when a named error about the recording ends the block:
    the dataset cannot be completed from that input, and rerunning rebuilds it. A failed
    write (disk full) and Ctrl-C keep what was written, readable, as the writer promises."""
    try:
        yield
    except BeadSightError as e:
        if not isinstance(e, WriteError):
            partial_path(out).unlink(missing_ok=True)
        raise


def _check_output(raw: Path, out: Path, overwrite: bool) -> None:
    """Never write over the recording being read; anything else only with ``overwrite``."""
    if out.exists() and out.resolve().parent == raw.resolve():
        raise OutputExistsError(
            f"{out}: is a file of the raw recording {raw} being processed; write the "
            "dataset somewhere else"
        )
    refuse_existing(out, overwrite)


def _recording_geometry(rec: Recording) -> SensorGeometry:
    meta = rec.metadata.get("geometry")
    if isinstance(meta, dict):
        return SensorGeometry.from_dict(meta)
    params = rec.metadata.get("experiment_parameters", {})
    kwargs = {}
    if "sensor_size" in params:
        kwargs["sensor_size_mm"] = float(np.asarray(params["sensor_size"]).reshape(-1)[0])
    if "contact_radius" in params:
        kwargs["finger_radius_mm"] = float(params["contact_radius"])
    if "radius" in params:
        kwargs["press_range_mm"] = float(params["radius"])
    return SensorGeometry(**kwargs)
