"""ROS 2 message contents for readings: one place for topic names, frames, units and
stamps, shared by the MCAP writer (``live/recording/mcap.py``), the ROS 2 publisher
(``live/outputs/ros2.py``) and the Foxglove server (``live/outputs/foxglove.py``).

Each function returns a plain dict laid out like the ROS 2 message (field names and
nesting as in the ``.msg`` definitions). Units follow ROS (REP 103): metres, newtons,
seconds; the pressure image stays in kPa (its ``encoding`` is ``32FC1``).

=========================  =====================================  ===============================
topic (under the namespace) type                                  content
=========================  =====================================  ===============================
``pressure``               ``sensor_msgs/msg/Image``              map, ``32FC1`` little-endian, kPa
``force``                  ``geometry_msgs/msg/WrenchStamped``    ``wrench.force.z`` = total normal
                                                                  force, N (other components 0)
``cop``                    ``geometry_msgs/msg/PointStamped``     centre of pressure, m (only when
                                                                  the map has pressure)
``contact_area``           ``geometry_msgs/msg/Vector3Stamped``   ``vector.x`` = contact area, m^2
                                                                  (y, z 0)
``health``                 ``diagnostic_msgs/msg/DiagnosticArray`` the sensor's state and its
                                                                  health with figures
``camera``                 ``sensor_msgs/msg/Image``              model-input frame, ``rgb8``
``reference_force``        ``geometry_msgs/msg/WrenchStamped``    true force when the source knows
                                                                  it (the simulator)
=========================  =====================================  ===============================

The ``beadsight`` frame: origin at the sensor centre, x and y along the printer's X and Y
axes (the calibration frame of ``beadsight.geometry``), z out of the pad; the map's row 0
is printer +Y, column 0 printer +X (see ``beadsight.geometry.mm_to_px``).
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Any

import numpy as np

from beadsight.live.config import ROS_NAMESPACE, check_namespace

DEFAULT_NAMESPACE = ROS_NAMESPACE  # topics and channels live under it (live/config.py)
__all__ = ["check_namespace"]  # re-exported: outputs check namespaces through msg

FRAME_ID = "beadsight"
PRESSURE, FORCE, COP, CONTACT_AREA, HEALTH, CAMERA, REFERENCE_FORCE = (
    "pressure",
    "force",
    "cop",
    "contact_area",
    "health",
    "camera",
    "reference_force",
)
RETAKE_REST = "retake_rest"  # the topic a robot writes to (std_msgs/msg/Empty): re-take rest
M_PER_MM = 1e-3
M2_PER_MM2 = 1e-6
NS_PER_S = 1_000_000_000
FLOAT32_BYTES = 4

# diagnostic_msgs/msg/DiagnosticStatus levels
DIAGNOSTIC_OK, DIAGNOSTIC_WARN, DIAGNOSTIC_ERROR, DIAGNOSTIC_STALE = 0, 1, 2, 3
SENSOR_STATUS = "beadsight: sensor"  # DiagnosticStatus.name of the sensor's state
HEALTH_STATUS = "beadsight: health"  # DiagnosticStatus.name of its drift health
SENSOR_LEVELS = {  # LiveStatus.state -> level (others: WARN)
    "starting": DIAGNOSTIC_OK,
    "ok": DIAGNOSTIC_OK,
    "warming_up": DIAGNOSTIC_OK,
    "no_signal": DIAGNOSTIC_STALE,
    "ended": DIAGNOSTIC_STALE,
    "stopped": DIAGNOSTIC_STALE,
    "error": DIAGNOSTIC_ERROR,
}
HEALTH_LEVELS = {"ok": DIAGNOSTIC_OK, "drifting": DIAGNOSTIC_WARN, "recalibrate": DIAGNOSTIC_ERROR}


def topic(namespace: str, name: str) -> str:
    """The ROS 2 topic ``<namespace>/<name>``, e.g. ``/beadsight/pressure``."""
    return f"{check_namespace(namespace)}/{name}"


def stamp(timestamp_s: float) -> tuple[int, int]:
    """Unix time in s -> (sec, nanosec): the float's exact value rounded to the nearest ns
    (``round(t * 1e9)`` would be up to 128 ns off: a float64 holds today's unix time in ns
    only to 256 ns)."""
    sec, nanosec = divmod(round(Fraction(timestamp_s) * NS_PER_S), NS_PER_S)
    return int(sec), int(nanosec)


def unix_ns(timestamp_s: float) -> int:
    """Unix time in s -> integer ns (log times of MCAP and Foxglove), see :func:`stamp`."""
    sec, nanosec = stamp(timestamp_s)
    return sec * NS_PER_S + nanosec


def header(timestamp_s: float) -> dict[str, Any]:
    """``std_msgs/msg/Header`` stamped ``timestamp_s`` (unix time, s)."""
    sec, nanosec = stamp(timestamp_s)
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": FRAME_ID}


def image_message(pressure_kpa: np.ndarray, timestamp_s: float) -> dict[str, Any]:
    """``sensor_msgs/msg/Image`` (32FC1, kPa) for an (H, W) map."""
    data = np.ascontiguousarray(pressure_kpa, dtype="<f4")
    h, w = data.shape
    return {
        "header": header(timestamp_s),
        "height": h,
        "width": w,
        "encoding": "32FC1",
        "is_bigendian": 0,
        "step": w * FLOAT32_BYTES,
        "data": data.tobytes(),
    }


def camera_message(frame_rgb: np.ndarray, timestamp_s: float) -> dict[str, Any]:
    """``sensor_msgs/msg/Image`` (rgb8) for an (H, W, 3) uint8 RGB frame."""
    data = np.ascontiguousarray(frame_rgb, dtype=np.uint8)
    h, w, _ = data.shape
    return {
        "header": header(timestamp_s),
        "height": h,
        "width": w,
        "encoding": "rgb8",
        "is_bigendian": 0,
        "step": w * 3,
        "data": data.tobytes(),
    }


def wrench_message(force_n: float, timestamp_s: float) -> dict[str, Any]:
    """``geometry_msgs/msg/WrenchStamped`` with force.z = total normal force (N)."""
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "header": header(timestamp_s),
        "wrench": {"force": {"x": 0.0, "y": 0.0, "z": float(force_n)}, "torque": zero},
    }


def point_message(cop_mm: np.ndarray, timestamp_s: float) -> dict[str, Any]:
    """``geometry_msgs/msg/PointStamped``: centre of pressure (x, y) mm -> metres, z = 0."""
    x_mm, y_mm = (float(v) for v in np.asarray(cop_mm).reshape(2))
    return {
        "header": header(timestamp_s),
        "point": {"x": x_mm * M_PER_MM, "y": y_mm * M_PER_MM, "z": 0.0},
    }


def area_message(contact_area_mm2: float, timestamp_s: float) -> dict[str, Any]:
    """``geometry_msgs/msg/Vector3Stamped``: ``vector.x`` = contact area in m^2 (y, z = 0).

    ROS 2's common messages have no stamped scalar for an area; Vector3Stamped is in every
    ROS install (``ros2 topic echo`` needs no package of ours) and carries the header, so the
    area has the capture time of its reading like every other topic."""
    area_m2 = float(contact_area_mm2) * M2_PER_MM2
    return {"header": header(timestamp_s), "vector": {"x": area_m2, "y": 0.0, "z": 0.0}}


def finite_or_none(value: Any) -> Any:
    """A figure for JSON and text: finite numbers as float/int, NaN/inf as None, bools and
    strings as they are, anything else as its ``str``."""
    if isinstance(value, (bool, str)) or value is None:
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return str(value)


def health_report(status: Any, health: Any, timestamp_s: float) -> dict[str, Any]:
    """What the health topic carries: the sensor's state and, when it is tracked, its health.

    status: a :class:`~beadsight.live.listeners.LiveStatus` (state, message, since_s), or
        None before the first one.
    health: the newest update's health (``.state`` one of :data:`HEALTH_LEVELS`,
        ``.figures`` a dict of named numbers, optionally ``.message``: what to do), or None
        where health is not tracked.
    Returns a JSON-ready dict: ``state``/``message``/``figures`` of the health (None, "",
    {} without one) and ``sensor_state``/``sensor_message``/``sensor_since_s``.
    """
    figures = dict(getattr(health, "figures", None) or {}) if health is not None else {}
    return {
        "timestamp_s": float(timestamp_s),
        "state": None if health is None else str(health.state),
        "message": "" if health is None else str(getattr(health, "message", "") or ""),
        "figures": {str(k): finite_or_none(v) for k, v in figures.items()},
        "sensor_state": "starting" if status is None else status.state,
        "sensor_message": "" if status is None else status.message,
        "sensor_since_s": None if status is None else float(status.since_s),
    }


def _diagnostic_status(level: int, name: str, message: str, values: dict) -> dict[str, Any]:
    """``diagnostic_msgs/msg/DiagnosticStatus`` (values as text, as ROS 2 has them)."""
    return {
        "level": int(level),
        "name": name,
        "message": message,
        "hardware_id": FRAME_ID,
        "values": [{"key": k, "value": "" if v is None else str(v)} for k, v in values.items()],
    }


def diagnostics_message(report: dict[str, Any]) -> dict[str, Any]:
    """``diagnostic_msgs/msg/DiagnosticArray`` of a :func:`health_report`: the status
    :data:`SENSOR_STATUS` (level from the sensor's state) and, when health is tracked,
    :data:`HEALTH_STATUS` (ok: OK, drifting: WARN, recalibrate: ERROR; its figures as
    values)."""
    sensor_state = report["sensor_state"]
    statuses = [
        _diagnostic_status(
            SENSOR_LEVELS.get(sensor_state, DIAGNOSTIC_WARN),
            SENSOR_STATUS,
            report["sensor_message"] or sensor_state,
            {"state": sensor_state, "since_s": report["sensor_since_s"]},
        )
    ]
    state = report["state"]
    if state is not None:
        statuses.append(
            _diagnostic_status(
                HEALTH_LEVELS.get(state, DIAGNOSTIC_WARN),
                HEALTH_STATUS,
                report["message"] or state,
                {"state": state, **report["figures"]},
            )
        )
    return {"header": header(report["timestamp_s"]), "status": statuses}
