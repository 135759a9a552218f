"""The ROS 2 message types of live readings, from one source: rosbags' type store.

The ROS 2 definitions (``sensor_msgs/msg/Image``, ...) are read from rosbags' store of a
ROS 2 distribution (:data:`STORE`), and from them are made both the ``.msg`` text an MCAP
file carries (:func:`message_definition`) and the Cyclone DDS structs ``--ros2`` writes
(:func:`idl_structs`). Nothing here writes a field list by hand. rosbags comes with the
``ros`` extra (``pip install 'beadsight[ros]'``); everything is imported on first use.
"""

from __future__ import annotations

import functools
import logging
import types
import typing
from dataclasses import dataclass
from typing import Any

from beadsight.errors import BeadSightError
from beadsight.live.ros import messages as msg

logger = logging.getLogger(__name__)

STORE = "ROS2_HUMBLE"  # rosbags' type store the definitions come from (stable since Humble)
# the ROS graph's discovery message (what rmw_cyclonedds publishes on ros_discovery_info);
# its Gid is char[24] up to Humble and uint8[16] since Iron: this follows Jazzy (the LTS)
DISCOVERY_STORE = "ROS2_JAZZY"
DISCOVERY_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"
TOPIC_TYPES = {  # topic name (under the namespace) -> ROS 2 type (see ros.messages)
    msg.PRESSURE: "sensor_msgs/msg/Image",
    msg.FORCE: "geometry_msgs/msg/WrenchStamped",
    msg.COP: "geometry_msgs/msg/PointStamped",
    msg.CONTACT_AREA: "geometry_msgs/msg/Vector3Stamped",
    msg.HEALTH: "diagnostic_msgs/msg/DiagnosticArray",
    msg.REFERENCE_FORCE: "geometry_msgs/msg/WrenchStamped",
    msg.CAMERA: "sensor_msgs/msg/Image",
}
COMMAND_TYPES = {msg.RETAKE_REST: "std_msgs/msg/Empty"}  # topics read (under the namespace)
# ROS 2 primitive -> Cyclone IDL type name in cyclonedds.idl.types (None: a Python type)
_PRIMITIVES = {
    "bool": None,
    "byte": "byte",
    "char": "uint8",  # ROS 2 maps char to uint8
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
    "string": None,
}


def _require(package: str, what: str) -> Any:
    import importlib

    try:
        return importlib.import_module(package)
    except ImportError:
        raise BeadSightError(
            f"{what} needs the '{package.split('.')[0]}' package: pip install 'beadsight[ros]'"
        ) from None


@functools.cache
def typestore(store: str = STORE) -> Any:
    """rosbags' type store ``store`` (default :data:`STORE`)."""
    typesys = _require("rosbags.typesys", "ROS 2 message types")
    return typesys.get_typestore(getattr(typesys.Stores, store))


def message_definition(ros_type: str) -> str:
    """The ``.msg`` text of ``ros_type`` as ``ros2 bag`` stores it in MCAP: the type's own
    fields, then each dependency after a ``MSG: pkg/Name`` line."""
    text, _md5 = typestore().generate_msgdef(ros_type, ros_version=2)
    return text


def dds_type_name(ros_type: str) -> str:
    """ROS 2 type -> its DDS type name: ``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_``."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@functools.cache
def idl_structs() -> dict[str, type]:
    """ROS 2 type -> Cyclone DDS IDL struct, for every type in :data:`TOPIC_TYPES` and
    :data:`COMMAND_TYPES` (and their fields' types, built on the way).
    ``sensor_msgs/msg/Image`` serialises its ``data`` fast where this Cyclone allows it
    (:func:`fast_byte_sequences`)."""
    _require("cyclonedds.idl", "--ros2")
    built: dict[str, type] = {}
    wanted = {*TOPIC_TYPES.values(), *COMMAND_TYPES.values()}
    for ros_type in sorted(wanted):
        _struct(ros_type, built)
    fast_byte_sequences(built["sensor_msgs/msg/Image"])
    return {t: built[t] for t in wanted}


@functools.cache
def discovery_struct() -> type:
    """The Cyclone DDS struct of :data:`DISCOVERY_TYPE` (from :data:`DISCOVERY_STORE`)."""
    _require("cyclonedds.idl", "--ros2")
    return _struct(DISCOVERY_TYPE, {}, DISCOVERY_STORE)


def gid_bytes() -> int:
    """Bytes of a ``rmw_dds_common/msg/Gid`` in :data:`DISCOVERY_STORE` (16 since Iron)."""
    _constants, fields = typestore(DISCOVERY_STORE).fielddefs["rmw_dds_common/msg/Gid"]
    (_name, (_kind, (_element, length))), *_ = fields
    return int(length)


def _struct(ros_type: str, built: dict[str, type], store: str = STORE) -> type:
    if ros_type in built:
        return built[ros_type]
    from cyclonedds.idl import IdlStruct

    _constants, fields = typestore(store).fielddefs[ros_type]
    annotations = {name: _field_type(desc, built, store) for name, desc in fields}
    cls = types.new_class(
        ros_type.rsplit("/", 1)[1],
        (IdlStruct,),
        {"typename": dds_type_name(ros_type)},
        lambda ns: ns.update(__annotations__=annotations, __module__=__name__),
    )
    built[ros_type] = dataclass(cls)
    return built[ros_type]


def _field_type(desc: tuple, built: dict[str, type], store: str = STORE) -> Any:
    """A rosbags field description (Nodetype, details) -> the Cyclone IDL annotation."""
    from cyclonedds.idl import types as idl
    from rosbags.typesys.base import Nodetype

    kind, rest = desc
    if kind == Nodetype.NAME:
        return _struct(rest, built, store)
    if kind == Nodetype.BASE:
        name, bound = rest
        if name == "string":
            return idl.bounded_str[bound] if bound else str
        if name not in _PRIMITIVES:
            raise BeadSightError(f"ROS 2 primitive {name!r}: no Cyclone DDS type for it")
        return bool if name == "bool" else getattr(idl, _PRIMITIVES[name])
    sub, length = rest
    element = _field_type(sub, built, store)
    if kind == Nodetype.ARRAY:
        return idl.array[element, length]
    return idl.sequence[element, length] if length else idl.sequence[element]


def fast_byte_sequences(image_type: type) -> bool:
    """Serialise ``Image.data`` from ``bytes`` in one copy; True where this worked.

    Cyclone's generic ``sequence<uint8>`` path packs the 262,144 bytes of a 256x256 map
    one argument each (~9 ms, holding the GIL); its ``bytes`` machine writes the same
    wire format (uint32 length, then the bytes) in ~0.3 ms. The declared type (and so
    the XTypes type information other participants see) stays ``sequence<uint8>``. This
    reaches into ``cyclonedds.idl._machinery``, a private module: the ``ros`` extra pins
    the Cyclone versions it was checked on, and where the layout differs, the slow path
    stays (logged once) and the bytes on the wire are the same.
    """
    try:
        from cyclonedds.idl._machinery import BytesMachine, PlainCdrV2SequenceOfPrimitiveMachine

        idl = image_type.__idl__
        idl.populate()
        machines = [(m, m.members_machines) for m in (idl.v1_machine, idl.v2_machine)]
        for _machine, members in machines:
            if not isinstance(members.get("data"), PlainCdrV2SequenceOfPrimitiveMachine):
                raise TypeError(f"Image.data is a {type(members.get('data')).__name__}")
        for _machine, members in machines:
            members["data"] = BytesMachine()
        return True
    except Exception as e:
        logger.warning("ros2: fast image serialisation unavailable (%s); publishing is slower", e)
        return False


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def build_struct(cls: type, value: Any) -> Any:
    """An IDL struct instance of ``cls`` from a message dict of :mod:`beadsight.live.ros.messages`
    (nested dicts and lists of dicts, laid out like the ROS 2 message)."""
    if not isinstance(value, dict):
        return value
    out = {}
    for name, sub in _hints(cls).items():
        item = value[name]
        if isinstance(item, list) and item and isinstance(item[0], dict):
            out[name] = [build_struct(typing.get_args(sub)[0], x) for x in item]
        else:
            out[name] = build_struct(sub, item)
    return cls(**out)
