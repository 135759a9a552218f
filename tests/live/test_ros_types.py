"""ROS 2 types from one source (issue 27, item 7): the Cyclone structs and the MCAP ``.msg``
text are generated from rosbags' type store, and the fast path for ``Image.data`` (which
reaches into Cyclone's private machinery) writes the same bytes as Cyclone's own path, and
falls back to it where the machinery is not as expected."""

from __future__ import annotations

import logging
import typing

import cyclonedds.idl  # noqa: F401  (the 'ros' extra: a missing one is an import error)
import numpy as np
import rosbags.typesys  # noqa: F401

from beadsight.live.ros import messages as msg
from beadsight.live.ros.types import (
    TOPIC_TYPES,
    _struct,
    build_struct,
    fast_byte_sequences,
    idl_structs,
    message_definition,
    typestore,
)

IMAGE = "sensor_msgs/msg/Image"


def _kpa(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 150, (64, 64)).astype(np.float32)


def _image(cls: type, seed: int = 0):
    return build_struct(cls, msg.image_message(_kpa(seed), 1_763_727_012.0334))


def test_every_struct_has_the_fields_of_the_rosbags_definition():
    structs = idl_structs()
    for ros_type in set(TOPIC_TYPES.values()):
        cls = structs[ros_type]
        _consts, fields = typestore().fielddefs[ros_type]
        assert list(typing.get_type_hints(cls)) == [name for name, _ in fields]
        package, _, name = ros_type.split("/")
        assert cls.__idl_typename__ == f"{package}::msg::dds_::{name}_"


def test_the_fast_image_path_writes_cyclones_own_bytes_and_rosbags_reads_them():
    fast = idl_structs()[IMAGE]
    slow = _struct(IMAGE, {})  # a fresh struct, never patched
    for seed in range(3):
        fast_bytes = _image(fast, seed).serialize(use_version_2=False)
        assert fast_bytes == _image(slow, seed).serialize(use_version_2=False)
        decoded = typestore().deserialize_cdr(fast_bytes, IMAGE)
        assert (decoded.encoding, decoded.height, decoded.width) == ("32FC1", 64, 64)
        assert decoded.data.tobytes() == _kpa(seed).astype("<f4").tobytes()


def test_an_unexpected_cyclone_layout_falls_back_to_the_slow_path(caplog):
    cls = _struct(IMAGE, {})
    assert fast_byte_sequences(cls) is True
    reference = _image(cls).serialize(use_version_2=False)
    with caplog.at_level(logging.WARNING, logger="beadsight.live.ros.types"):
        # patched already: Image.data is no longer Cyclone's sequence machine
        assert fast_byte_sequences(cls) is False
    assert "ros2: fast image serialisation unavailable (Image.data is a BytesMachine)" in (
        caplog.text
    )
    assert _image(cls).serialize(use_version_2=False) == reference  # still the same bytes


def test_mcap_definitions_are_rosbags_ros2_text():
    text = message_definition("geometry_msgs/msg/WrenchStamped")
    assert text.startswith("std_msgs/Header header\ngeometry_msgs/Wrench wrench\n")
    assert "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec" in text
