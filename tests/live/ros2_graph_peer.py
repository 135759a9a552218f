"""An independent look at the ROS 2 graph for the tests: what ``ros2 node list`` reads.

Subscribes to ``ros_discovery_info`` the way ROS 2's rmw layer does (reliable,
transient-local, keep last 1), with its own IDL for ``rmw_dds_common/msg/Gid``,
``NodeEntitiesInfo`` and ``ParticipantEntitiesInfo`` written from the ROS 2 interface
definitions (Iron and later: ``uint8[16] data``), not taken from beadsight; and reads the
DDS built-in DCPSPublication topic (every writer's GUID, participant and topic). Prints one
JSON line per discovery sample (``"info"``) and per writer (``"writer"``); stops after
SECONDS, or once a participant announced a node named NODE and its writers were seen.

    python ros2_graph_peer.py DOMAIN NODE SECONDS

(No ``from __future__ import annotations``: Cyclone reads these classes' annotations.)
"""

import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, bounded_str, sequence, uint8
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: array[uint8, 16]


@dataclass
class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: bounded_str[256]
    node_name: bounded_str[256]
    reader_gid_seq: sequence[Gid]
    writer_gid_seq: sequence[Gid]


@dataclass
class ParticipantEntitiesInfo(
    IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
):
    gid: Gid
    node_entities_info_seq: sequence[NodeEntitiesInfo]


QOS = Qos(
    Policy.Reliability.Reliable(duration(seconds=1)),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
)


def hexgid(g: Gid) -> str:
    return bytes(g.data).hex()


def main() -> None:
    domain, node, seconds = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    dp = DomainParticipant(domain)
    info = DataReader(dp, Topic(dp, "ros_discovery_info", ParticipantEntitiesInfo), qos=QOS)
    writers = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
    print(json.dumps({"ready": True}), flush=True)
    end, seen = time.monotonic() + seconds, set()
    announced: set[str] = set()
    while time.monotonic() < end:
        for s in info.take(N=64):
            nodes = [
                {
                    "namespace": n.node_namespace,
                    "name": n.node_name,
                    "readers": [hexgid(g) for g in n.reader_gid_seq],
                    "writers": [hexgid(g) for g in n.writer_gid_seq],
                }
                for n in s.node_entities_info_seq
            ]
            print(json.dumps({"info": {"gid": hexgid(s.gid), "nodes": nodes}}), flush=True)
            if any(n["name"] == node for n in nodes):
                announced.update(w for n in nodes for w in n["writers"])
        for w in writers.take(N=256):
            guid, participant = w.key.bytes.hex(), w.participant_key.bytes.hex()
            seen.add(guid)
            print(
                json.dumps(
                    {"writer": {"guid": guid, "participant": participant, "topic": w.topic_name}}
                ),
                flush=True,
            )
        if announced and announced <= seen:
            break
        time.sleep(0.02)


if __name__ == "__main__":
    main()
