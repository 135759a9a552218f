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
from dataclasses import dataclass
from typing import Any

from beadsight.errors import BeadSightError
from beadsight.live.ros import messages as msg

logger = logging.getLogger(__name__)

STORE = "ROS2_HUMBLE"  # rosbags' type store the definitions come from (stable since Humble)
TOPIC_TYPES = {  # topic name (under the namespace) -> ROS 2 type (see ros.messages)
    msg.PRESSURE: "sensor_msgs/msg/Image",
    msg.FORCE: "geometry_msgs/msg/WrenchStamped",
    msg.COP: "geometry_msgs/msg/PointStamped",
    msg.CONTACT_AREA: "geometry_msgs/msg/Vector3Stamped",
    msg.HEALTH: "diagnostic_msgs/msg/DiagnosticArray",
    msg.REFERENCE_FORCE: "geometry_msgs/msg/WrenchStamped",
    msg.CAMERA: "sensor_msgs/msg/Image",
}
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
def typestore() -> Any:
    """rosbags' type store of :data:`STORE`."""
    typesys = _require("rosbags.typesys", "ROS 2 message types")
    return typesys.get_typestore(getattr(typesys.Stores, STORE))


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
    """ROS 2 type -> Cyclone DDS IDL struct, for every type in :data:`TOPIC_TYPES` (and their
    fields' types, built on the way). ``sensor_msgs/msg/Image`` serialises its ``data``
    fast where this Cyclone allows it (:func:`fast_byte_sequences`)."""
    _require("cyclonedds.idl", "--ros2")
    built: dict[str, type] = {}
    for ros_type in sorted(set(TOPIC_TYPES.values())):
        _struct(ros_type, built)
    fast_byte_sequences(built["sensor_msgs/msg/Image"])
    return {t: built[t] for t in TOPIC_TYPES.values()}


def _struct(ros_type: str, built: dict[str, type]) -> type:
    if ros_type in built:
        return built[ros_type]
    from cyclonedds.idl import IdlStruct

    _constants, fields = typestore().fielddefs[ros_type]
    annotations = {name: _field_type(desc, built) for name, desc in fields}
    cls = types.new_class(
        ros_type.rsplit("/", 1)[1],
        (IdlStruct,),
        {"typename": dds_type_name(ros_type)},
        lambda ns: ns.update(__annotations__=annotations, __module__=__name__),
    )
    built[ros_type] = dataclass(cls)
    return built[ros_type]


def _field_type(desc: tuple, built: dict[str, type]) -> Any:
    """A rosbags field description (Nodetype, details) -> the Cyclone IDL annotation."""
    from cyclonedds.idl import types as idl
    from rosbags.typesys.base import Nodetype

    kind, rest = desc
    if kind == Nodetype.NAME:
        return _struct(rest, built)
    if kind == Nodetype.BASE:
        name, bound = rest
        if name == "string":
            return idl.bounded_str[bound] if bound else str
        if name not in _PRIMITIVES:
            raise BeadSightError(f"ROS 2 primitive {name!r}: no Cyclone DDS type for it")
        return bool if name == "bool" else getattr(idl, _PRIMITIVES[name])
    sub, length = rest
    if kind == Nodetype.ARRAY:
        return idl.array[_field_type(sub, built), length]
    return (
        idl.sequence[_field_type(sub, built), length]
        if length
        else idl.sequence[_field_type(sub, built)]
    )


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
