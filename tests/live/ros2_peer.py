"""An independent ROS 2 subscriber for the tests: its own IDL types, its own process.

The message types below are written from the ROS 2 interface definitions
(builtin_interfaces/Time, std_msgs/Header, sensor_msgs/Image, geometry_msgs/Vector3,
Wrench, WrenchStamped, Point, PointStamped, std_msgs/Float32, diagnostic_msgs/KeyValue,
DiagnosticStatus, DiagnosticArray) with the DDS names ROS 2's rosidl generates, not
taken from beadsight. It subscribes the way ROS 2 nodes do: the sensor-data profile
(best effort, keep last 5) on the maps and the default profile (reliable, keep last 10)
on force, and prints one JSON line per message received.

    python ros2_peer.py DOMAIN NAMESPACE SECONDS
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import byte, float32, float64, int32, sequence, uint8, uint32
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
class Float32(IdlStruct, typename="std_msgs::msg::dds_::Float32_"):
    data: float32


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


def summary(name: str, m) -> dict:
    if name == "pressure":
        data = bytes(m.data)
        return {
            "t": stamp(m.header),
            "frame": m.header.frame_id,
            "enc": m.encoding,
            "h": m.height,
            "w": m.width,
            "step": m.step,
            "big": m.is_bigendian,
            "sha": hashlib.sha256(data).hexdigest(),
            "len": len(data),
        }
    if name == "force":
        f = m.wrench.force
        return {"t": stamp(m.header), "frame": m.header.frame_id, "fx": f.x, "fy": f.y, "fz": f.z}
    if name == "cop":
        return {"t": stamp(m.header), "x": m.point.x, "y": m.point.y, "z": m.point.z}
    if name == "contact_area":
        return {"area_m2": m.data}
    if name == "health":
        s = m.status[0]
        return {
            "level": s.level,
            "name": s.name,
            "message": s.message,
            "values": {kv.key: kv.value for kv in s.values},
        }
    raise KeyError(name)


def main() -> None:
    domain, namespace, seconds = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    dp = DomainParticipant(domain)
    readers = {}
    for name, cls, qos in (
        ("pressure", Image, SENSOR_DATA),
        ("force", WrenchStamped, DEFAULT),
        ("cop", PointStamped, SENSOR_DATA),
        ("contact_area", Float32, DEFAULT),
        ("health", DiagnosticArray, DEFAULT),
    ):
        topic = Topic(dp, f"rt{namespace}/{name}", cls)
        readers[name] = DataReader(dp, topic, qos=qos)
    print(json.dumps({"ready": True}), flush=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for name, reader in readers.items():
            for m in reader.take(N=64):
                print(json.dumps({"topic": name, **summary(name, m)}), flush=True)
        time.sleep(0.01)


if __name__ == "__main__":
    main()
