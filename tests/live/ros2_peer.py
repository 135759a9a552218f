"""An independent ROS 2 subscriber for the tests: its own IDL types, its own process.

The message types below are written from the ROS 2 interface definitions
(builtin_interfaces/Time, std_msgs/Header, sensor_msgs/Image, geometry_msgs/Vector3,
Vector3Stamped, Wrench, WrenchStamped, Point, PointStamped, diagnostic_msgs/KeyValue,
DiagnosticStatus, DiagnosticArray) with the DDS names ROS 2's rosidl generates, not
taken from beadsight. It subscribes the way ROS 2 nodes do: the sensor-data profile
(best effort, keep last 5) on the images and the CoP, the default profile (reliable,
keep last 10) on the rest, and prints one JSON line per message received. It stops
after SECONDS, or once the health topic reports the sensor ended or stopped.

    python ros2_peer.py DOMAIN NAMESPACE SECONDS [--camera] [--retake]

``--retake``: first write one std_msgs/msg/Empty to NAMESPACE/retake_rest (reliable), as a
robot asking for a new rest reference does.

(No ``from __future__ import annotations``: Cyclone reads these classes' annotations.)
"""

import hashlib
import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import byte, float64, int32, sequence, uint8, uint32
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: uint32
    width: uint32
    encoding: str
    is_bigendian: uint8
    step: uint32
    data: sequence[uint8]


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3
    torque: Vector3


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header
    wrench: Wrench


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class PointStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PointStamped_"):
    header: Header
    point: Point


@dataclass
class Vector3Stamped(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3Stamped_"):
    header: Header
    vector: Vector3


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: byte
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: sequence[DiagnosticStatus]


@dataclass
class Empty(IdlStruct, typename="std_msgs::msg::dds_::Empty_"):
    structure_needs_at_least_one_member: uint8  # rosidl gives an empty message one member


SENSOR_DATA = Qos(
    Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile
)
DEFAULT = Qos(
    Policy.Reliability.Reliable(duration(seconds=0.1)),
    Policy.History.KeepLast(10),
    Policy.Durability.Volatile,
)


def stamp(h: Header) -> float:
    return h.stamp.sec + h.stamp.nanosec * 1e-9


def _stamped(m) -> dict:
    """The header of a stamped message: its time (s) and frame."""
    return {"t": stamp(m.header), "frame": m.header.frame_id}


def _image(m: Image) -> dict:
    data = bytes(m.data)
    return {
        **_stamped(m),
        "enc": m.encoding,
        "h": m.height,
        "w": m.width,
        "step": m.step,
        "big": m.is_bigendian,
        "sha": hashlib.sha256(data).hexdigest(),
        "len": len(data),
    }


def _wrench(m: WrenchStamped) -> dict:
    f, q = m.wrench.force, m.wrench.torque
    return {
        **_stamped(m),
        "force": [f.x, f.y, f.z],
        "torque": [q.x, q.y, q.z],
    }


def _diagnostics(m: DiagnosticArray) -> dict:
    return {
        **_stamped(m),
        "status": [
            {
                "level": s.level,
                "name": s.name,
                "message": s.message,
                "hardware_id": s.hardware_id,
                "values": {kv.key: kv.value for kv in s.values},
            }
            for s in m.status
        ],
    }


SUMMARIES = {
    "pressure": _image,
    "camera": _image,
    "force": _wrench,
    "reference_force": _wrench,
    "cop": lambda m: {
        **_stamped(m),
        "point": [m.point.x, m.point.y, m.point.z],
    },
    "contact_area": lambda m: {
        **_stamped(m),
        "vector": [m.vector.x, m.vector.y, m.vector.z],
    },
    "health": _diagnostics,
}
TOPICS = {  # name -> (type, QoS of the subscription)
    "pressure": (Image, SENSOR_DATA),
    "force": (WrenchStamped, DEFAULT),
    "cop": (PointStamped, SENSOR_DATA),
    "contact_area": (Vector3Stamped, DEFAULT),
    "health": (DiagnosticArray, DEFAULT),
    "reference_force": (WrenchStamped, DEFAULT),
    "camera": (Image, SENSOR_DATA),
}
ENDED = ("ended", "stopped", "error")


def drain(readers: dict) -> bool:
    """Print what arrived; True once the health topic says the sensor ended."""
    ended = False
    for name, reader in readers.items():
        for m in reader.take(N=64):
            if isinstance(m, InvalidSample):  # the writer went away (no data)
                continue
            print(json.dumps({"topic": name, **SUMMARIES[name](m)}), flush=True)
            if name == "health":
                values = {kv.key: kv.value for kv in m.status[0].values}
                ended |= values.get("state") in ENDED
    return ended


def main() -> None:
    domain, namespace, seconds = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    names = [n for n in TOPICS if n != "camera" or "--camera" in sys.argv[4:]]
    dp = DomainParticipant(domain)
    readers = {}
    for name in names:
        cls, qos = TOPICS[name]
        readers[name] = DataReader(dp, Topic(dp, f"rt{namespace}/{name}", cls), qos=qos)
    print(json.dumps({"ready": True}), flush=True)
    end = time.monotonic() + seconds
    if "--retake" in sys.argv[4:]:  # as `ros2 topic pub --once <ns>/retake_rest std_msgs/msg/Empty`
        writer = DataWriter(dp, Topic(dp, f"rt{namespace}/retake_rest", Empty), qos=DEFAULT)
        while not writer.get_matched_subscriptions() and time.monotonic() < end:
            time.sleep(0.01)
        writer.write(Empty(0))
        print(json.dumps({"topic": "retake_sent"}), flush=True)
    while time.monotonic() < end:
        if drain(readers):  # what was written before the end may still be on its way
            time.sleep(0.3)
            drain(readers)
            break
        time.sleep(0.01)


if __name__ == "__main__":
    main()
