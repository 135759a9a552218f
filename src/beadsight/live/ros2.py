"""Live readings as ROS 2 topics over DDS, without a ROS install (``beadsight live --ros2``).

Publishes with Cyclone DDS (``pip install 'beadsight[ros]'``) the way a ROS 2 node does,
so ``ros2 topic echo /beadsight/force`` on the same network (any RMW, any DDS vendor)
receives it:

* DDS topic ``rt<namespace>/<name>`` (``rt/beadsight/pressure``) for the ROS 2 topic
  ``<namespace>/<name>``; type names ``<pkg>::msg::dds_::<Type>_``
  (``sensor_msgs::msg::dds_::Image_``); plain CDR (XCDR1), as ROS 2 uses.
* QoS: reliable, keep last :data:`HISTORY_DEPTH`, volatile. Both ROS 2 profiles match it:
  ``SensorDataQoS`` (best effort, keep last 5) and the default (reliable, keep last 10).
  A subscriber asking for transient-local durability does not match (nothing is latched).

Topics, message contents and units are those of :mod:`beadsight.live.ros_messages`
(the same as the MCAP export). Publishing runs on its own thread
(:class:`~beadsight.live.publisher.BackgroundPublisher`): a slow network drops old
readings (counted in ``dropped``) instead of slowing sensing.
"""

from __future__ import annotations

import logging
import time
import types
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np

from beadsight.errors import BeadSightError
from beadsight.live import ros_messages as msg
from beadsight.live.publisher import DEFAULT_QUEUE_SIZE, BackgroundPublisher

logger = logging.getLogger(__name__)

HISTORY_DEPTH = 5  # samples the writer keeps for late acknowledgements
MAX_BLOCKING_S = 0.05  # a reliable write waits at most this long for a slow reader
DDS_TOPIC_PREFIX = "rt"  # ROS 2 maps topic /a/b to DDS topic rt/a/b

STATUS_LEVELS = {
    "starting": msg.DIAGNOSTIC_OK,
    "ok": msg.DIAGNOSTIC_OK,
    "warming_up": msg.DIAGNOSTIC_OK,
    "no_signal": msg.DIAGNOSTIC_STALE,
    "ended": msg.DIAGNOSTIC_STALE,
    "stopped": msg.DIAGNOSTIC_STALE,
    "error": msg.DIAGNOSTIC_ERROR,
}


def _types() -> dict[str, Any]:
    """The ROS 2 message types as Cyclone DDS IDL structs (imported on first use)."""
    try:
        from cyclonedds.idl import IdlStruct
        from cyclonedds.idl.types import byte, float32, float64, int32, sequence, uint8, uint32
    except ImportError:
        raise BeadSightError(
            "--ros2 needs Cyclone DDS (the 'cyclonedds' package): pip install 'beadsight[ros]'"
        ) from None

    def struct(typename: str, **fields: Any) -> type:
        name = typename.rsplit("::", 1)[1]
        cls = types.new_class(
            name,
            (IdlStruct,),
            {"typename": typename},
            lambda ns: ns.update(__annotations__=fields, __module__=__name__),
        )
        return dataclass(cls)

    time_ = struct("builtin_interfaces::msg::dds_::Time_", sec=int32, nanosec=uint32)
    header = struct("std_msgs::msg::dds_::Header_", stamp=time_, frame_id=str)
    image = struct(
        "sensor_msgs::msg::dds_::Image_",
        header=header,
        height=uint32,
        width=uint32,
        encoding=str,
        is_bigendian=uint8,
        step=uint32,
        data=sequence[uint8],
    )
    vector3 = struct("geometry_msgs::msg::dds_::Vector3_", x=float64, y=float64, z=float64)
    wrench = struct("geometry_msgs::msg::dds_::Wrench_", force=vector3, torque=vector3)
    point = struct("geometry_msgs::msg::dds_::Point_", x=float64, y=float64, z=float64)
    key_value = struct("diagnostic_msgs::msg::dds_::KeyValue_", key=str, value=str)
    status = struct(
        "diagnostic_msgs::msg::dds_::DiagnosticStatus_",
        level=byte,
        name=str,
        message=str,
        hardware_id=str,
        values=sequence[key_value],
    )
    by_ros_type = {
        "sensor_msgs/msg/Image": image,
        "geometry_msgs/msg/WrenchStamped": struct(
            "geometry_msgs::msg::dds_::WrenchStamped_", header=header, wrench=wrench
        ),
        "geometry_msgs/msg/PointStamped": struct(
            "geometry_msgs::msg::dds_::PointStamped_", header=header, point=point
        ),
        "std_msgs/msg/Float32": struct("std_msgs::msg::dds_::Float32_", data=float32),
        "diagnostic_msgs/msg/DiagnosticArray": struct(
            "diagnostic_msgs::msg::dds_::DiagnosticArray_", header=header, status=sequence[status]
        ),
    }
    _fast_byte_sequences(image)
    return by_ros_type


def _fast_byte_sequences(image_type: type) -> None:
    """Serialise ``Image.data`` from ``bytes`` in one copy.

    Cyclone's generic ``sequence<uint8>`` path packs the 262,144 bytes of a 256x256 map
    one argument each (~9 ms, holding the GIL); its ``bytes`` machine writes the same
    wire format (uint32 length, then the bytes) in ~0.3 ms. The declared type (and so
    the XTypes type information other participants see) stays ``sequence<uint8>``.
    If this Cyclone version is laid out differently, the slow path stays.
    """
    try:
        from cyclonedds.idl._machinery import BytesMachine, PlainCdrV2SequenceOfPrimitiveMachine

        idl = image_type.__idl__
        idl.populate()
        for machine in (idl.v1_machine, idl.v2_machine):
            members = machine.members_machines
            if not isinstance(members.get("data"), PlainCdrV2SequenceOfPrimitiveMachine):
                raise TypeError(type(members.get("data")).__name__)
            members["data"] = BytesMachine()
    except Exception as e:  # pragma: no cover - other Cyclone versions
        logger.warning("ros2: fast image serialisation unavailable (%s); publishing is slower", e)


def _build(cls: type, value: Any) -> Any:
    """An IDL struct instance from a ros_messages dict (nested dicts and lists of dicts)."""
    fields = getattr(cls, "__dataclass_fields__", None)
    if fields is None or not isinstance(value, dict):
        return value
    hints = typing.get_type_hints(cls)
    out = {}
    for name in fields:
        sub = hints.get(name)
        item = value[name]
        if isinstance(item, list) and item and isinstance(item[0], dict):
            out[name] = [_build(typing.get_args(sub)[0], x) for x in item]
        else:
            out[name] = _build(sub, item) if isinstance(item, dict) else item
    return cls(**out)


def default_qos() -> Any:
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.Reliable(duration(seconds=MAX_BLOCKING_S)),
        Policy.History.KeepLast(HISTORY_DEPTH),
        Policy.Durability.Volatile,
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


class Ros2Publisher(BackgroundPublisher):
    """Publishes each live update as ROS 2 messages (a ``LiveListener``).

    namespace: ROS 2 namespace of the topics (``/beadsight``).
    domain_id: the ROS_DOMAIN_ID to publish in (0..232).
    camera: also publish the model-input frame (``<namespace>/camera``, rgb8).
    """

    name = "ros2"

    def __init__(
        self,
        namespace: str = msg.DEFAULT_NAMESPACE,
        domain_id: int = 0,
        camera: bool = False,
        queue_size: int = DEFAULT_QUEUE_SIZE,
    ):
        if not 0 <= domain_id <= 232:
            raise BeadSightError(f"ROS domain id {domain_id}: expected 0..232 (ROS_DOMAIN_ID)")
        self.namespace = msg.check_namespace(namespace)
        self.domain_id = domain_id
        self.camera = camera
        self._types = _types()
        from cyclonedds.domain import DomainParticipant

        self._participant = DomainParticipant(domain_id)
        self._writers: dict[str, tuple[Any, type]] = {}
        for name, ros_type in (
            (msg.PRESSURE, "sensor_msgs/msg/Image"),
            (msg.FORCE, "geometry_msgs/msg/WrenchStamped"),
            (msg.COP, "geometry_msgs/msg/PointStamped"),
            (msg.CONTACT_AREA, "std_msgs/msg/Float32"),
            (msg.HEALTH, "diagnostic_msgs/msg/DiagnosticArray"),
            (msg.REFERENCE_FORCE, "geometry_msgs/msg/WrenchStamped"),
            *([(msg.CAMERA, "sensor_msgs/msg/Image")] if camera else []),
        ):
            self._writers[name] = self._writer(name, self._types[ros_type])
        super().__init__(queue_size)

    def _writer(self, name: str, cls: type) -> tuple[Any, type]:
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        dds_topic = DDS_TOPIC_PREFIX + msg.topic(self.namespace, name)
        topic = Topic(self._participant, dds_topic, cls, qos=default_qos())
        return DataWriter(self._participant, topic, qos=default_qos()), cls

    def topics(self) -> dict[str, str]:
        """ROS 2 topic name -> ROS 2 type of everything this publisher writes."""
        return {
            msg.topic(self.namespace, name): cls.__idl_typename__.replace("::msg::dds_::", "/msg/")[
                :-1
            ]
            for name, (_w, cls) in self._writers.items()
        }

    def _write(self, name: str, message: dict[str, Any]) -> None:
        writer, cls = self._writers[name]
        writer.write(_build(cls, message))

    def publish(self, update: Any) -> None:
        r = update.reading
        t = float(r.timestamp_s)
        self._write(msg.PRESSURE, msg.image_message(r.pressure_kpa, t))
        self._write(msg.FORCE, msg.wrench_message(r.force_n, t))
        cop = np.asarray(r.cop_mm, dtype=np.float64).reshape(2)
        if np.all(np.isfinite(cop)):
            self._write(msg.COP, msg.point_message(cop, t))
        self._write(msg.CONTACT_AREA, msg.area_message(r.contact_area_mm2))
        if np.isfinite(update.reference_force_n):
            self._write(msg.REFERENCE_FORCE, msg.wrench_message(update.reference_force_n, t))
        if self.camera:
            self._write(msg.CAMERA, msg.camera_message(update.frame_rgb, t))

    def publish_status(self, status: Any) -> None:
        level = STATUS_LEVELS.get(status.state, msg.DIAGNOSTIC_WARN)
        values = {"state": status.state, "since_s": f"{status.since_s:.3f}"}
        self._write(msg.HEALTH, msg.diagnostics_message(level, status.message, values, time.time()))

    def close(self) -> None:
        self._writers.clear()
        participant, self._participant = self._participant, None
        if participant is not None:
            del participant  # Cyclone deletes the participant and its writers when collected
