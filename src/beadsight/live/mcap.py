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
``/beadsight/reference_force`` ``geometry_msgs/msg/WrenchStamped``  true force when the
                                                                source knows it (sim)
=============================  ===============================  ==========================

The ``beadsight`` frame: origin at the sensor centre, x and y along the printer's X and Y
axes (the calibration frame of ``beadsight.geometry``), z out of the pad; the map's row 0
is printer +Y, column 0 printer +X (see ``beadsight.geometry.mm_to_px``).
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from beadsight import __version__
from beadsight.config import SensorGeometry
from beadsight.errors import BeadSightError, ConfigError
from beadsight.live.readings import ReadingLike, open_readings

logger = logging.getLogger(__name__)

FRAME_ID = "beadsight"
TOPIC_PRESSURE = "/beadsight/pressure"
TOPIC_FORCE = "/beadsight/force"
TOPIC_COP = "/beadsight/cop"
TOPIC_REFERENCE_FORCE = "/beadsight/reference_force"
M_PER_MM = 1e-3
NS_PER_S = 1_000_000_000
FLOAT32_BYTES = 4

_SEP = "\n" + "=" * 80 + "\n"
_HEADER = (
    "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id"
    + _SEP
    + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec"
)
_VECTOR3 = "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z"

# ROS 2 message definitions as ros2 bag stores them: the type's text, then each dependency.
MESSAGE_DEFINITIONS = {
    "sensor_msgs/msg/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data" + _SEP + _HEADER
    ),
    "geometry_msgs/msg/WrenchStamped": (
        "std_msgs/Header header\ngeometry_msgs/Wrench wrench"
        + _SEP
        + "MSG: geometry_msgs/Wrench\ngeometry_msgs/Vector3 force\ngeometry_msgs/Vector3 torque"
        + _SEP
        + _VECTOR3
        + _SEP
        + _HEADER
    ),
    "geometry_msgs/msg/PointStamped": (
        "std_msgs/Header header\ngeometry_msgs/Point point"
        + _SEP
        + "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z"
        + _SEP
        + _HEADER
    ),
}


def _require_mcap() -> tuple[Any, Any]:
    try:
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer
    except ImportError as e:
        raise BeadSightError(
            f"MCAP export needs the 'mcap' and 'mcap-ros2-support' packages ({e.name} is "
            "missing): pip install 'beadsight[ros]'"
        ) from None
    return Writer, CompressionType


def _header(timestamp_s: float) -> dict[str, Any]:
    ns = round(timestamp_s * NS_PER_S)
    return {"stamp": {"sec": ns // NS_PER_S, "nanosec": ns % NS_PER_S}, "frame_id": FRAME_ID}


def image_message(pressure_kpa: np.ndarray, timestamp_s: float) -> dict[str, Any]:
    """``sensor_msgs/msg/Image`` (32FC1, kPa) for an (H, W) map."""
    data = np.ascontiguousarray(pressure_kpa, dtype="<f4")
    h, w = data.shape
    return {
        "header": _header(timestamp_s),
        "height": h,
        "width": w,
        "encoding": "32FC1",
        "is_bigendian": 0,
        "step": w * FLOAT32_BYTES,
        "data": data.tobytes(),
    }


def wrench_message(force_n: float, timestamp_s: float) -> dict[str, Any]:
    """``geometry_msgs/msg/WrenchStamped`` with force.z = total normal force (N)."""
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "header": _header(timestamp_s),
        "wrench": {"force": {"x": 0.0, "y": 0.0, "z": float(force_n)}, "torque": zero},
    }


def point_message(cop_mm: np.ndarray, timestamp_s: float) -> dict[str, Any]:
    """``geometry_msgs/msg/PointStamped``: centre of pressure (x, y) mm -> metres, z = 0."""
    x_mm, y_mm = (float(v) for v in np.asarray(cop_mm).reshape(2))
    return {
        "header": _header(timestamp_s),
        "point": {"x": x_mm * M_PER_MM, "y": y_mm * M_PER_MM, "z": 0.0},
    }


class McapReadingsWriter:
    """Write readings as ROS 2 messages to an MCAP file (same interface as ReadingsWriter).

    Writes ``<path>.partial`` and renames it on :meth:`close`. Not thread-safe.
    """

    def __init__(
        self,
        path: str | Path,
        geometry: SensorGeometry,
        provenance: dict[str, Any] | None = None,
    ):
        writer_cls, compression = _require_mcap()
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.geometry = geometry
        self._stream = open(self.partial, "wb")  # noqa: SIM115 - closed in close()/abort()
        self._writer = writer_cls(self._stream, compression=compression.ZSTD)
        self._schemas = {
            name: self._writer.register_msgdef(name, text)
            for name, text in MESSAGE_DEFINITIONS.items()
        }
        self._writer.add_metadata(
            "beadsight",
            {
                "beadsight_version": __version__,
                "geometry": geometry.to_json(),
                "provenance": json.dumps(provenance or {}, default=str),
                "units": "pressure kPa, force N, position m",
            },
        )
        self._count = 0
        self._closed = False

    def __len__(self) -> int:
        return self._count

    def _write(self, topic: str, schema: str, message: dict, time_ns: int) -> None:
        self._writer.write_message(
            topic,
            self._schemas[schema],
            message,
            log_time=time_ns,
            publish_time=time_ns,
            sequence=self._count,
        )

    def append(
        self,
        reading: ReadingLike,
        reference_force_n: float = math.nan,
        latency_s: float | None = None,
    ) -> None:
        """Write one reading's messages (``latency_s`` is accepted for interface parity)."""
        t = float(reading.timestamp_s)
        t_ns = round(t * NS_PER_S)
        self._write(
            TOPIC_PRESSURE, "sensor_msgs/msg/Image", image_message(reading.pressure_kpa, t), t_ns
        )
        self._write(
            TOPIC_FORCE, "geometry_msgs/msg/WrenchStamped", wrench_message(reading.force_n, t), t_ns
        )
        cop = np.asarray(reading.cop_mm, dtype=np.float64).reshape(2)
        if np.all(np.isfinite(cop)):
            self._write(TOPIC_COP, "geometry_msgs/msg/PointStamped", point_message(cop, t), t_ns)
        if math.isfinite(reference_force_n):
            self._write(
                TOPIC_REFERENCE_FORCE,
                "geometry_msgs/msg/WrenchStamped",
                wrench_message(reference_force_n, t),
                t_ns,
            )
        self._count += 1

    def close(self) -> Path:
        if not self._closed:
            self._closed = True
            self._writer.finish()
            self._stream.close()
            os.replace(self.partial, self.path)
            logger.info("wrote %d readings to %s", self._count, self.path)
        return self.path

    def abort(self) -> None:
        """Finish the MCAP summary but leave the file as ``<path>.partial``."""
        if not self._closed:
            self._closed = True
            self._writer.finish()
            self._stream.close()

    def __enter__(self) -> McapReadingsWriter:
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class _Row:
    """One reading of a readings file, shaped like ``beadsight.inference.predictor.Reading``."""

    def __init__(self, rf, i: int):
        self.pressure_kpa = rf.pressure_kpa[i]
        self.force_n = float(rf.force_n[i])
        self.cop_mm = rf.cop_mm[i]
        self.has_contact = bool(rf.has_contact[i])
        self.contact_area_mm2 = float(rf.contact_area_mm2[i])
        self.timestamp_s = float(rf.timestamp_s[i])
        self.latency_s = float(rf.latency_s[i])
        self.frame_index = int(rf.frame_index[i])


def export_mcap(readings_path: str | Path, out_path: str | Path, progress: bool = True) -> Path:
    """Convert a readings HDF5 file (``beadsight live --output x.h5``) to MCAP. Returns out_path."""
    readings_path, out_path = Path(readings_path), Path(out_path)
    if readings_path.resolve() == out_path.resolve():
        raise ConfigError(f"{out_path}: the MCAP output would overwrite its input")
    with open_readings(readings_path) as rf:
        provenance = {**rf.provenance, "converted_from": str(readings_path)}
        with McapReadingsWriter(out_path, rf.geometry, provenance) as writer:
            for i in tqdm(range(len(rf)), desc="to-mcap", unit="reading", disable=not progress):
                writer.append(_Row(rf, i), float(rf.reference_force_n[i]))
    return out_path
