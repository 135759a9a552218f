"""``--ros2`` on the ROS 2 graph: the node ROS tools see (``ros_discovery_info``, read by an
independent subscriber in another process, tests/live/ros2_graph_peer.py, and decoded by
rosbags), and a warning when another publisher writes on our topics."""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.live import wait_until

from beadsight.live.ros import messages as msg

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads

GRAPH_PEER = Path(__file__).with_name("ros2_graph_peer.py")
TOPICS = ("pressure", "force", "cop", "contact_area", "health", "reference_force")


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "another publisher" in r.getMessage()]


def _publisher(domain: int, namespace: str = msg.DEFAULT_NAMESPACE):
    from beadsight.live.outputs.ros2 import Ros2Publisher

    return Ros2Publisher(namespace, domain)


def test_the_node_is_announced_on_ros_discovery_info(dds):
    """A subscriber in another process, with its own IDL of rmw_dds_common's messages and
    ROS 2's QoS for the topic, receives our node (namespace, name) with the gids of exactly
    the writers DDS discovery shows for our participant."""
    domain, _ = dds
    publisher = _publisher(domain)
    try:
        peer = subprocess.run(
            [sys.executable, str(GRAPH_PEER), str(domain), "beadsight", "30"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        participant = publisher.guid.bytes.hex()
        ours = {w.guid.bytes.hex() for w, _cls in publisher._writers.values()}
    finally:
        publisher.finish()
    assert peer.returncode == 0, peer.stderr
    lines = [json.loads(line) for line in peer.stdout.splitlines()]
    infos = [m["info"] for m in lines if "info" in m and m["info"]["gid"] == participant]
    assert infos, f"no ros_discovery_info from our participant {participant}: {lines[:5]}"
    (node,) = infos[-1]["nodes"]
    assert (node["namespace"], node["name"]) == ("/beadsight", "beadsight")
    assert node["readers"] == []
    # every writer DDS announced for our participant, and nothing else
    writers = {
        m["writer"]["guid"]: m["writer"]["topic"]
        for m in lines
        if "writer" in m and m["writer"]["participant"] == participant
    }
    assert set(node["writers"]) == set(writers)
    assert ours < set(node["writers"])  # the topics' writers, and the discovery writer
    topics = {writers[g] for g in ours}
    assert topics == {f"rt/beadsight/{n}" for n in TOPICS}
    assert {writers[g] for g in set(node["writers"]) - ours} == {"ros_discovery_info"}


def test_discovery_message_decodes_with_rosbags(dds):
    """The bytes of our ros_discovery_info sample (XCDR1) decode with rosbags' Jazzy store:
    the participant's gid (its GUID, 16 bytes), one node, the writers' gids."""
    from rosbags.typesys import Stores, get_typestore

    from beadsight.live.ros.types import DISCOVERY_TYPE, build_struct, discovery_struct

    domain, _ = dds
    publisher = _publisher(domain, "/left_finger")
    try:
        raw = build_struct(discovery_struct(), publisher.graph.info).serialize(use_version_2=False)
        participant = publisher.guid.bytes
        writers = {w.guid.bytes for w, _cls in publisher._writers.values()}
    finally:
        publisher.finish()
    decoded = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(raw, DISCOVERY_TYPE)
    assert bytes(decoded.gid.data) == participant
    (node,) = decoded.node_entities_info_seq
    assert (node.node_namespace, node.node_name) == ("/left_finger", "beadsight")
    assert writers < {bytes(g.data) for g in node.writer_gid_seq}


def test_a_second_publisher_on_our_topics_is_named_in_a_warning(dds, caplog):
    """Two publishers with one namespace in one domain: each warns, once, naming the topics
    and the other's participant, process and node; another namespace is no conflict."""
    domain, _ = dds
    caplog.set_level(logging.WARNING, logger="beadsight.live.outputs.ros2_graph")
    first = _publisher(domain)
    elsewhere = _publisher(domain, "/right_finger")
    second = _publisher(domain)
    try:
        wait_until(lambda: first.graph.others() and second.graph.others(), 20, "discovery")
        wait_until(lambda: len(first.graph.others()[0].topics) == 6, 20, "every topic")
        (other,) = first.graph.others()
        assert other.participant == second.guid
        assert other.topics == tuple(sorted(f"/beadsight/{n}" for n in TOPICS))
        assert f"pid {os.getpid()} on {socket.gethostname()}" in other.process
        wait_until(lambda: first.graph.others()[0].nodes, 20, "its node")
        assert first.graph.others()[0].nodes == ("/beadsight/beadsight",)
        wait_until(lambda: len(_warnings(caplog)) >= 2, 10, "a warning by each")
        assert elsewhere.graph.others() == []
    finally:
        for p in (first, elsewhere, second):
            p.finish()
    warnings = _warnings(caplog)
    assert len(warnings) == 2, warnings  # one by each of the two, none by /right_finger
    by_first = next(w for w in warnings if str(second.guid) in w)
    topics = ", ".join(sorted(f"/beadsight/{n}" for n in TOPICS))
    assert by_first.startswith(f"ros2: another publisher writes on {topics}: ")
    assert f"DDS participant {second.guid} (" in by_first
    assert f"pid {os.getpid()} on {socket.gethostname()}" in by_first
    assert "another --ros-namespace or --ros-domain" in by_first
