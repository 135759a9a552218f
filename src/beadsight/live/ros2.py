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

import functools
import inspect
import logging
import os
import types
import typing
from collections.abc import Mapping
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
MAX_DOMAIN_ID = 232  # the highest ROS_DOMAIN_ID whose DDS ports fit (ROS 2 docs: Linux)
DOMAIN_ENV = "ROS_DOMAIN_ID"
MISSING = "--ros2 needs Cyclone DDS (the 'cyclonedds' package): pip install 'beadsight[ros]'"

TOPIC_TYPES = {  # topic name (under the namespace) -> ROS 2 type, as in ros_messages
    msg.PRESSURE: "sensor_msgs/msg/Image",
    msg.FORCE: "geometry_msgs/msg/WrenchStamped",
    msg.COP: "geometry_msgs/msg/PointStamped",
    msg.CONTACT_AREA: "std_msgs/msg/Float32",
    msg.HEALTH: "diagnostic_msgs/msg/DiagnosticArray",
    msg.REFERENCE_FORCE: "geometry_msgs/msg/WrenchStamped",
    msg.CAMERA: "sensor_msgs/msg/Image",
}


def require_cyclonedds() -> None:
    """Raise a one-line :class:`BeadSightError` naming the extra if Cyclone DDS is missing."""
    try:
        import cyclonedds.domain  # noqa: F401
    except ImportError:
        raise BeadSightError(MISSING) from None


def check_domain(domain_id: int, where: str = "ROS domain id") -> int:
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise BeadSightError(f"{where} {domain_id}: expected 0..{MAX_DOMAIN_ID}")
    return domain_id


def domain_from_environment(environ: Mapping[str, str] = os.environ) -> int:
    """The ROS 2 domain as ROS 2 nodes pick it: ``$ROS_DOMAIN_ID`` if set, else 0."""
    text = environ.get(DOMAIN_ENV, "").strip()
    if not text:
        return 0
    try:
        value = int(text)
    except ValueError:
        raise BeadSightError(
            f"{DOMAIN_ENV}={text!r}: expected an integer 0..{MAX_DOMAIN_ID}"
        ) from None
    return check_domain(value, DOMAIN_ENV)


def check_options(**options: Any) -> dict[str, Any]:
    """Refuse now what ``Ros2Publisher(**options)`` would refuse later (Cyclone DDS not
    installed, a bad namespace or domain, an unknown option); returns ``options``."""
    try:
        bound = inspect.signature(Ros2Publisher).bind(**options)
    except TypeError as e:
        raise BeadSightError(f"ROS 2 options {sorted(options)}: {e}") from None
    bound.apply_defaults()
    msg.check_namespace(bound.arguments["namespace"])
    check_domain(bound.arguments["domain_id"])
    require_cyclonedds()
    return options


@functools.cache
def _types() -> dict[str, Any]:
    """The ROS 2 message types as Cyclone DDS IDL structs (imported on first use)."""
    try:
        from cyclonedds.idl import IdlStruct
        from cyclonedds.idl.types import byte, float32, float64, int32, sequence, uint8, uint32
    except ImportError:
        raise BeadSightError(MISSING) from None

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


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _build(cls: type, value: Any) -> Any:
    """An IDL struct instance from a ros_messages dict (nested dicts and lists of dicts)."""
    if not isinstance(value, dict):
        return value
    hints = _hints(cls)
    out = {}
    for name, sub in hints.items():
        item = value[name]
        if isinstance(item, list) and item and isinstance(item[0], dict):
            out[name] = [_build(typing.get_args(sub)[0], x) for x in item]
        else:
            out[name] = _build(sub, item)
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
    domain_id: the ROS_DOMAIN_ID to publish in (0..232; see :func:`domain_from_environment`).
    camera: also publish the model-input frame (``<namespace>/camera``, rgb8).
    Cyclone DDS reads its network settings from ``$CYCLONEDDS_URI`` as usual.
    """

    name = "ros2"

    def __init__(
        self,
        namespace: str = msg.DEFAULT_NAMESPACE,
        domain_id: int = 0,
        camera: bool = False,
        queue_size: int = DEFAULT_QUEUE_SIZE,
    ):
        self.namespace = msg.check_namespace(namespace)
        self.domain_id = check_domain(domain_id)
        self.camera = camera
        types_ = _types()
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        self._participant = DomainParticipant(domain_id)
        self._entities: list[Any] = []  # topics and writers, deleted in close()
        self._writers: dict[str, tuple[Any, type]] = {}
        qos = default_qos()
        for name, ros_type in TOPIC_TYPES.items():
            if name == msg.CAMERA and not camera:
                continue
            cls = types_[ros_type]
            topic = Topic(self._participant, DDS_TOPIC_PREFIX + self._topic(name), cls, qos=qos)
            writer = DataWriter(self._participant, topic, qos=qos)
            self._entities += [writer, topic]
            self._writers[name] = (writer, cls)
        super().__init__(queue_size)

    def _topic(self, name: str) -> str:
        return msg.topic(self.namespace, name)

    def topics(self) -> dict[str, str]:
        """ROS 2 topic name -> ROS 2 type of everything this publisher writes."""
        return {self._topic(name): TOPIC_TYPES[name] for name in self._writers}

    def subscribers(self) -> dict[str, int]:
        """ROS 2 topic name -> how many subscriptions (any node, any vendor) match it now."""
        return {
            self._topic(name): len(writer.get_matched_subscriptions())
            for name, (writer, _cls) in self._writers.items()
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

    def publish_health(self, report: dict[str, Any]) -> None:
        self._write(msg.HEALTH, msg.diagnostics_message(report))

    def close(self) -> None:
        """Delete the writers, topics and participant now (Cyclone would on collection);
        deleting a writer first lets reliable readers acknowledge what it wrote."""
        self._writers.clear()
        entities, self._entities = self._entities, []
        participant, self._participant = self._participant, None
        for entity in [*entities, participant]:
            if entity is not None:
                entity.__del__()  # dds_delete; idempotent (Cyclone tracks deleted entities)
