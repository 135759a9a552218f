"""``--ros2`` on the ROS 2 graph: a node that ROS tools see, and other publishers on our topics.

* **A node for ``ros2 node list`` and ``ros2 topic info -v``.** ROS 2 tools learn which node
  owns which DDS reader and writer from the ``ros_discovery_info`` topic (no ``rt``
  prefix; type ``rmw_dds_common/msg/ParticipantEntitiesInfo``; reliable, transient-local,
  keep last 1), where rmw_cyclonedds publishes, per participant, its gid and its nodes
  with their namespace, name and reader/writer gids. :class:`RosGraph` publishes the same
  for one node, :data:`NODE_NAME` in the topics' namespace, owning every writer of the
  publisher. A gid is the entity's DDS GUID (16 bytes, as rmw_cyclonedds makes it; the
  Gid of Iron and later, :data:`~beadsight.live.ros.types.DISCOVERY_STORE`).
* **Another publisher on our topics.** Two ``live --ros2`` with one namespace in one domain
  would interleave their readings on the same topics. DDS discovery announces every
  writer (the built-in topic DCPSPublication); a writer of another participant on one of
  our topics is logged as a warning once per participant (:data:`WARN_AFTER_S` after its
  first writer is seen, so that it names them all), naming the topics, the
  participant (its GUID, process, pid and host from its discovery data) and its ROS
  nodes where it announces them; :meth:`RosGraph.others` lists them.
"""

from __future__ import annotations

import logging
import threading
import uuid
from dataclasses import dataclass
from typing import Any

from beadsight.live.ros.types import build_struct, discovery_struct, gid_bytes

logger = logging.getLogger(__name__)

DISCOVERY_TOPIC = "ros_discovery_info"  # DDS topic name, as rmw_dds_common has it
NODE_NAME = "beadsight"  # our node: <namespace>/beadsight
ENCLAVE_USER_DATA = b"enclave=/;"  # the participant user data rmw_cyclonedds sets
TAKE_AT_ONCE = 256  # built-in samples taken per call
WARN_AFTER_S = 0.5  # a new participant's writers arrive over a moment: warn once they have


def gid(guid: uuid.UUID) -> dict[str, Any]:
    """``rmw_dds_common/msg/Gid`` of a DDS entity: its GUID, zero-padded to the Gid's size."""
    size = gid_bytes()
    return {"data": list(guid.bytes.ljust(size, b"\0")[:size])}


def entities_info(
    participant: uuid.UUID,
    namespace: str,
    node_name: str,
    writers: list[uuid.UUID],
    readers: list[uuid.UUID] = (),
) -> dict[str, Any]:
    """``rmw_dds_common/msg/ParticipantEntitiesInfo`` of one node (as a message dict)."""
    node = {
        "node_namespace": namespace,
        "node_name": node_name,
        "reader_gid_seq": [gid(g) for g in readers],
        "writer_gid_seq": [gid(g) for g in writers],
    }
    return {"gid": gid(participant), "node_entities_info_seq": [node]}


def discovery_qos() -> Any:
    """What ROS 2 uses for ``ros_discovery_info``: reliable, transient-local, keep last 1."""
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(1),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


@dataclass(frozen=True)
class OtherPublisher:
    """Another participant writing on some of our topics."""

    participant: uuid.UUID
    topics: tuple[str, ...]  # ROS 2 topic names
    process: str  # "NAME pid N on HOST" from its discovery data ("" if it gave none)
    nodes: tuple[str, ...]  # its ROS nodes' full names, where it announces them

    def describe(self) -> str:
        who = f"DDS participant {self.participant}"
        if self.process:
            who += f" ({self.process})"
        if self.nodes:
            who += f", ROS node {', '.join(self.nodes)}"
        return who


class RosGraph:
    """Announce our node on ``participant`` and watch for other writers on ``topics``.

    topics: DDS topic name -> ROS 2 topic name, of our writers. writers, readers: our
    DataWriters and DataReaders (the node owns them).
    The participant must have been made with :func:`participant_qos`. :meth:`entities`
    lists the DDS entities made here (to delete before the participant).
    """

    def __init__(
        self,
        participant: Any,
        namespace: str,
        topics: dict[str, str],
        writers: list[Any],
        readers: list[Any] = (),
    ):
        from cyclonedds.builtin import (
            BuiltinDataReader,
            BuiltinTopicDcpsParticipant,
            BuiltinTopicDcpsPublication,
        )
        from cyclonedds.core import Listener
        from cyclonedds.pub import DataWriter
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        self._participant = participant
        self._guid = participant.guid
        self._topics = dict(topics)
        self._lock = threading.Lock()
        self._others: dict[uuid.UUID, set[str]] = {}
        self._warned: set[uuid.UUID] = set()
        self._timers: list[threading.Timer] = []
        cls, qos = discovery_struct(), discovery_qos()
        self._info_topic = Topic(participant, DISCOVERY_TOPIC, cls, qos=qos)
        self._info_writer = DataWriter(participant, self._info_topic, qos=qos)
        self._info_reader = DataReader(participant, self._info_topic, qos=qos)
        self._peers = BuiltinDataReader(participant, BuiltinTopicDcpsParticipant)
        self._publications = BuiltinDataReader(
            participant,
            BuiltinTopicDcpsPublication,
            listener=Listener(on_data_available=lambda _reader: self._check()),
        )
        self.info = entities_info(
            self._guid,
            namespace,
            NODE_NAME,
            [w.guid for w in [*writers, self._info_writer]],
            [r.guid for r in readers],
        )
        self._info_writer.write(build_struct(cls, self.info))
        self._check()

    def close(self) -> None:
        """Stop pending warnings (before the entities are deleted)."""
        with self._lock:
            timers, self._timers = self._timers, []
        for timer in timers:
            timer.cancel()
            if timer is not threading.current_thread():
                timer.join()

    def entities(self) -> list[Any]:
        return [
            self._publications,
            self._peers,
            self._info_reader,
            self._info_writer,
            self._info_topic,
        ]

    def _check(self) -> None:
        """Take new DCPSPublication samples; warn about new participants writing our topics."""
        try:
            samples = self._publications.take(N=TAKE_AT_ONCE)
        except Exception:  # the reader is being deleted
            return
        with self._lock:
            for s in samples:
                topic = self._topics.get(getattr(s, "topic_name", None))
                participant = getattr(s, "participant_key", None)
                if topic is None or participant is None or participant == self._guid:
                    continue
                self._others.setdefault(participant, set()).add(topic)
                if participant not in self._warned:
                    self._warned.add(participant)
                    timer = threading.Timer(WARN_AFTER_S, self._warn, (participant,))
                    timer.daemon = True
                    self._timers.append(timer)
                    timer.start()

    def _warn(self, participant: uuid.UUID) -> None:
        try:
            other = self._describe(participant)
        except Exception:  # closed meanwhile
            return
        logger.warning(
            "ros2: another publisher writes on %s: %s. Its readings and ours interleave "
            "on these topics; give one of them another --ros-namespace or --ros-domain",
            ", ".join(other.topics),
            other.describe(),
        )

    def others(self) -> list[OtherPublisher]:
        """Other participants seen writing on our topics so far."""
        self._check()
        with self._lock:
            participants = list(self._others)
        return [self._describe(p) for p in participants]

    def _describe(self, participant: uuid.UUID) -> OtherPublisher:
        with self._lock:
            topics = tuple(sorted(self._others.get(participant, ())))
        return OtherPublisher(
            participant, topics, self._process(participant), self._nodes(participant)
        )

    def _process(self, participant: uuid.UUID) -> str:
        """ "NAME pid N on HOST" from the participant's discovery data (Cyclone sends it)."""
        for sample in self._peers.read(N=TAKE_AT_ONCE):
            if getattr(sample, "key", None) != participant:
                continue
            props = {}
            for policy in sample.qos or ():
                if type(policy).__name__ == "Property":
                    props[policy.key] = policy.value
            name, pid, host = (props.get(k) for k in ("__ProcessName", "__Pid", "__Hostname"))
            if name or pid or host:
                return f"{name or 'process'} pid {pid or '?'} on {host or '?'}"
        return ""

    def _nodes(self, participant: uuid.UUID) -> tuple[str, ...]:
        """Full names of the ROS nodes ``participant`` announces on ros_discovery_info."""
        wanted = gid(participant)["data"]
        names = []
        for sample in self._info_reader.read(N=TAKE_AT_ONCE):
            if list(getattr(getattr(sample, "gid", None), "data", ())) != wanted:
                continue
            for node in sample.node_entities_info_seq:
                ns = node.node_namespace.rstrip("/")
                names.append(f"{ns}/{node.node_name}")
        return tuple(names)


def participant_qos() -> Any:
    """The participant's QoS: the user data rmw_cyclonedds sets (its security enclave)."""
    from cyclonedds.qos import Policy, Qos

    return Qos(Policy.Userdata(ENCLAVE_USER_DATA))
