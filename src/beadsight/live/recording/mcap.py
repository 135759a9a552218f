"""Readings as MCAP files with ROS 2 message types (``pip install 'beadsight[ros]'``).

Topics (all stamped with the capture time of the frame that produced the reading,
``header.frame_id = "beadsight"``; the MCAP log and publish times are the same instant):

=============================  ===============================  ==========================
topic                          type                             content
=============================  ===============================  ==========================
``/beadsight/pressure``        ``sensor_msgs/msg/Image``        pressure map, ``32FC1``,
                                                                little-endian, kPa
``/beadsight/force``           ``geometry_msgs/msg/WrenchStamped``  ``wrench.force.z`` =
                                                                total normal force, N
                                                                (other components 0)
``/beadsight/cop``             ``geometry_msgs/msg/PointStamped``   centre of pressure, m;
                                                                only for readings that
                                                                have one (non-zero map)
``/beadsight/contact_area``    ``geometry_msgs/msg/Vector3Stamped``  ``vector.x`` =
                                                                contact area, m^2
``/beadsight/reference_force`` ``geometry_msgs/msg/WrenchStamped``  true force when the
                                                                source knows it (sim)
``/beadsight/health``          ``diagnostic_msgs/msg/DiagnosticArray``  the sensor's state
                                                                and drift health, on each
                                                                change and once a second
                                                                (live recordings only: a
                                                                readings file keeps none)
=============================  ===============================  ==========================

The ``beadsight`` frame: origin at the sensor centre, x and y along the printer's X and Y
axes (the calibration frame of ``beadsight.geometry``), z out of the pad; the map's row 0
is printer +Y, column 0 printer +X (see ``beadsight.geometry.mm_to_px``).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from beadsight import __version__
from beadsight.errors import BeadSightError, ConfigError
from beadsight.live.recording.partial import PartialWriter, ReadingLike
from beadsight.live.recording.readings import open_readings
from beadsight.live.ros import messages as msg
from beadsight.live.ros.messages import (
    area_message,
    diagnostics_message,
    image_message,
    point_message,
    unix_ns,
    wrench_message,
)
from beadsight.live.ros.types import TOPIC_TYPES, message_definition

logger = logging.getLogger(__name__)

TOPIC_PRESSURE = msg.topic(msg.DEFAULT_NAMESPACE, msg.PRESSURE)
TOPIC_FORCE = msg.topic(msg.DEFAULT_NAMESPACE, msg.FORCE)
TOPIC_COP = msg.topic(msg.DEFAULT_NAMESPACE, msg.COP)
TOPIC_REFERENCE_FORCE = msg.topic(msg.DEFAULT_NAMESPACE, msg.REFERENCE_FORCE)
TOPIC_CONTACT_AREA = msg.topic(msg.DEFAULT_NAMESPACE, msg.CONTACT_AREA)
TOPIC_HEALTH = msg.topic(msg.DEFAULT_NAMESPACE, msg.HEALTH)
CHUNK_BYTES = 1024 * 1024  # messages are compressed and written in chunks of about this size
MESSAGE_OVERHEAD_BYTES = 512  # most bytes a message adds to an MCAP file beyond its payload
SUMMARY_BYTES = 16 * 1024  # MCAP summary without chunk indexes (schemas, channels, ...)
SUMMARY_BYTES_PER_CHUNK = 512  # its chunk index entry per chunk
MCAP_MAGIC = b"\x89MCAP0\r\n"


def _require_mcap() -> tuple[Any, Any]:
    try:
        import rosbags.typesys  # noqa: F401 - the message definitions (live.ros.types)
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer
    except ImportError as e:
        raise BeadSightError(
            f"MCAP export needs the 'mcap', 'mcap-ros2-support' and 'rosbags' packages "
            f"({e.name} is missing): pip install 'beadsight[ros]'"
        ) from None
    return Writer, CompressionType


class _CountedFile:
    """The MCAP writer's output: an unbuffered file that counts the bytes that reached it.

    A write that fails (disk full) is cut back off the file, so the file always ends with
    whole records; ``failed`` is then set.
    """

    def __init__(self, path: Path, exclusive: bool):
        self._f = open(path, "xb" if exclusive else "wb", buffering=0)  # noqa: SIM115
        self.written = 0
        self.failed = False

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        try:
            while view:
                view = view[self._f.write(view) :]
        except OSError:
            self.failed = True
            self._f.truncate(self.written)
            self._f.seek(self.written)
            raise
        self.written += len(data)
        return len(data)

    def tell(self) -> int:
        return self.written

    def flush(self) -> None:
        pass

    def end_without_summary(self) -> None:
        """End a file cut short by a failed write so that MCAP readers take it: DataEnd and
        a footer that announces no summary (readers then scan the records)."""
        from mcap.data_stream import RecordBuilder
        from mcap.records import DataEnd, Footer

        builder = RecordBuilder()
        DataEnd(0).write(builder)
        Footer(0, 0, 0).write(builder)
        builder.write(MCAP_MAGIC)
        self.failed = False
        self.write(builder.end())

    def close(self) -> None:
        self._f.close()


class McapReadingsWriter(PartialWriter):
    """Write readings as ROS 2 messages to an MCAP file (same interface as ReadingsWriter).

    Writes ``<path>.partial`` and renames it on :meth:`close`; an existing ``path`` is
    refused unless ``overwrite``. A full disk stops the recording with a
    :class:`~beadsight.files.WriteError` (see :mod:`beadsight.live.recording.recorder`); the file
    then ends properly after the last reading. Not thread-safe.
    """

    def _prepare(self) -> None:
        self._writer_cls, self._compression = _require_mcap()
        self._stream: _CountedFile | None = None
        self._pending = 0  # most bytes of messages in the writer's open (unwritten) chunk
        self._chunks = 0  # chunks written (each adds an index entry to the summary)

    def _create(self, provenance: dict | None) -> None:
        self._stream = _CountedFile(self.partial, exclusive=not self.overwrite)
        self._created = True
        self._writer = self._writer_cls(
            self._stream, chunk_size=CHUNK_BYTES, compression=self._compression.ZSTD
        )
        self._schemas = {
            name: self._writer.register_msgdef(name, message_definition(name))
            for name in sorted(set(TOPIC_TYPES.values()))
        }
        self._writer.add_metadata(
            "beadsight",
            {
                "beadsight_version": __version__,
                "geometry": self.geometry.to_json(),
                "provenance": json.dumps(provenance or {}, default=str),
                "units": "pressure kPa, force N, position m",
            },
        )

    def _messages(
        self, reading: ReadingLike, reference_force_n: float, health: dict[str, Any] | None
    ) -> list[tuple]:
        """(topic, schema, message) of one reading (and of ``health``, a health report)."""
        t = float(reading.timestamp_s)
        area = area_message(reading.contact_area_mm2, t)
        out = [
            (TOPIC_PRESSURE, TOPIC_TYPES[msg.PRESSURE], image_message(reading.pressure_kpa, t)),
            (TOPIC_FORCE, TOPIC_TYPES[msg.FORCE], wrench_message(reading.force_n, t)),
            (TOPIC_CONTACT_AREA, TOPIC_TYPES[msg.CONTACT_AREA], area),
        ]
        cop = np.asarray(reading.cop_mm, dtype=np.float64).reshape(2)
        if np.all(np.isfinite(cop)):
            out.append((TOPIC_COP, TOPIC_TYPES[msg.COP], point_message(cop, t)))
        if math.isfinite(reference_force_n):
            reference = wrench_message(reference_force_n, t)
            out.append((TOPIC_REFERENCE_FORCE, TOPIC_TYPES[msg.REFERENCE_FORCE], reference))
        if health is not None:
            out.append((TOPIC_HEALTH, TOPIC_TYPES[msg.HEALTH], diagnostics_message(health)))
        return out

    @staticmethod
    def _size(message: dict) -> int:
        """Most bytes ``message`` adds to a chunk (payload plus record and index overhead;
        a health message's text counted from its JSON, an upper bound of its CDR)."""
        if "status" in message:
            return len(json.dumps(message, default=str)) + MESSAGE_OVERHEAD_BYTES
        return len(message.get("data", b"")) + MESSAGE_OVERHEAD_BYTES

    def _write_messages(self, messages: list[tuple], t_ns: int) -> None:
        for topic, schema, message in messages:
            before = self._stream.written
            self._writer.write_message(
                topic,
                self._schemas[schema],
                message,
                log_time=t_ns,
                publish_time=t_ns,
                sequence=self._count,
            )
            if self._stream.written != before:  # the chunk (with this message) was written
                self._pending, self._chunks = 0, self._chunks + 1
                self._written = self._count + (message is messages[-1][2])
            else:
                self._pending += self._size(message)

    def _add(
        self,
        reading: ReadingLike,
        reference_force_n: float,
        latency_s: float | None,
        health: dict[str, Any] | None,
    ) -> None:
        """Write one reading's messages (``latency_s`` is accepted for interface parity);
        all are logged at the reading's capture time."""
        messages = self._messages(reading, reference_force_n, health)
        need = (
            self._pending
            + sum(self._size(m) for _t, _s, m in messages)
            + SUMMARY_BYTES
            + SUMMARY_BYTES_PER_CHUNK * (self._chunks + 1)
        )
        room = self._room()
        if need > room:
            self._written = self._count  # the clean stop below writes the open chunk
            self._disk_full(room, "the next reading")
        t_ns = unix_ns(float(reading.timestamp_s))
        self._guard(lambda: self._write_messages(messages, t_ns))

    def _close_file(self, flush: bool) -> None:
        stream, self._stream = self._stream, None
        if stream is None:
            return
        try:
            if not stream.failed:
                self._writer.finish()  # the open chunk and the summary: room was kept for them
                self._written = self._count
            else:
                stream.end_without_summary()
        finally:
            stream.close()


class _Row:
    """One reading of a readings file, shaped like ``beadsight.inference.predictor.PressureReading``."""

    def __init__(self, rf, i: int):
        self.pressure_kpa = rf.pressure_kpa[i]
        self.force_n = float(rf.force_n[i])
        self.cop_mm = rf.cop_mm[i]
        self.has_contact = bool(rf.has_contact[i])
        self.contact_area_mm2 = float(rf.contact_area_mm2[i])
        self.timestamp_s = float(rf.timestamp_s[i])
        self.latency_s = float(rf.latency_s[i])
        self.frame_index = int(rf.frame_index[i])


def export_mcap(
    readings_path: str | Path,
    out_path: str | Path,
    progress: bool = True,
    overwrite: bool = False,
) -> Path:
    """Convert a readings HDF5 file (``beadsight live --output x.h5``) to MCAP. Returns out_path.

    An existing ``out_path`` is refused unless ``overwrite``.
    """
    readings_path, out_path = Path(readings_path), Path(out_path)
    if readings_path.resolve() == out_path.resolve():
        raise ConfigError(f"{out_path}: the MCAP output would overwrite its input")
    with open_readings(readings_path) as rf:
        provenance = {**rf.provenance, "converted_from": str(readings_path)}
        with McapReadingsWriter(out_path, rf.geometry, provenance, overwrite=overwrite) as writer:
            for i in tqdm(range(len(rf)), desc="to-mcap", unit="reading", disable=not progress):
                writer.append(_Row(rf, i), float(rf.reference_force_n[i]))
    return out_path
