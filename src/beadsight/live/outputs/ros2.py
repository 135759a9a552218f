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

One topic is read: a message (``std_msgs/msg/Empty``) on ``<namespace>/retake_rest``
asks for a new rest reference (``on_retake_rest``; docs/live.md, "The rest reference").
It is read reliably, so a command is not lost: a publisher with ROS 2's default profile
(as ``ros2 topic pub``) matches, a best-effort one does not.

Topics, message contents and units are those of :mod:`beadsight.live.ros.messages`
(the same as the MCAP export). Publishing runs on its own thread
(:class:`~beadsight.live.outputs.base.OutputListener`): a slow network skips readings
(counted in ``skipped``) instead of slowing sensing, and none older than ``max_age_s`` goes out.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from beadsight.errors import BeadSightError
from beadsight.live.config import MAX_AGE_S, MAX_DOMAIN_ID, check_domain, check_namespace
from beadsight.live.outputs.base import DEFAULT_QUEUE_SIZE, OutputListener
from beadsight.live.outputs.ros2_graph import RosGraph, participant_qos
from beadsight.live.ros import messages as msg
from beadsight.live.ros.types import COMMAND_TYPES, TOPIC_TYPES, build_struct, idl_structs

logger = logging.getLogger(__name__)

HISTORY_DEPTH = 5  # samples the writer keeps for late acknowledgements
MAX_BLOCKING_S = 0.05  # a reliable write waits at most this long for a slow reader
DDS_TOPIC_PREFIX = "rt"  # ROS 2 maps topic /a/b to DDS topic rt/a/b
DOMAIN_ENV = "ROS_DOMAIN_ID"
MISSING = "--ros2 needs Cyclone DDS (the 'cyclonedds' package): pip install 'beadsight[ros]'"


def require_cyclonedds() -> None:
    """Raise a one-line :class:`BeadSightError` naming the extra if Cyclone DDS is missing."""
    try:
        import cyclonedds.domain  # noqa: F401
    except ImportError:
        raise BeadSightError(MISSING) from None


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


def default_qos() -> Any:
    """Reliable, keep last :data:`HISTORY_DEPTH`, volatile, XCDR1 (module docstring): what
    the topics are written with and the command topic is read with."""
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.Reliable(duration(seconds=MAX_BLOCKING_S)),
        Policy.History.KeepLast(HISTORY_DEPTH),
        Policy.Durability.Volatile,
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


class Ros2Publisher(OutputListener):
    """Publishes each live update as ROS 2 messages (a ``LiveListener``).

    namespace: ROS 2 namespace of the topics (``/beadsight``).
    domain_id: the ROS_DOMAIN_ID to publish in (0..232; see :func:`domain_from_environment`).
    camera: also publish the model-input frame (``<namespace>/camera``, rgb8).
    max_age_s, queue_size: the slow-client rule (:class:`~beadsight.live.outputs.base.OutputListener`).
    on_retake_rest: called (on a Cyclone thread) once per batch of messages that arrive
    together on ``<namespace>/retake_rest`` (``std_msgs/msg/Empty``), e.g.
    :meth:`~beadsight.live.sensor.LiveSensor.retake_rest`; None: the topic is not read.
    Cyclone DDS reads its network settings from ``$CYCLONEDDS_URI`` as usual.
    """

    name = "ros2"

    def __init__(
        self,
        namespace: str = msg.DEFAULT_NAMESPACE,
        domain_id: int = 0,
        camera: bool = False,
        max_age_s: float = MAX_AGE_S,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        on_retake_rest: Callable[[], None] | None = None,
    ):
        self.namespace = check_namespace(namespace)
        self.domain_id = check_domain(domain_id)
        self.camera = camera
        types_ = idl_structs()
        from cyclonedds.core import Listener
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.pub import DataWriter
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        self._participant = DomainParticipant(domain_id, qos=participant_qos())
        self.guid = self._participant.guid  # the DDS participant's GUID (its gid in ROS 2)
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
        self.on_retake_rest = on_retake_rest
        self.retake_requests = 0  # messages received on <namespace>/retake_rest
        readers = []
        if on_retake_rest is not None:
            cls = types_[COMMAND_TYPES[msg.RETAKE_REST]]
            name = DDS_TOPIC_PREFIX + self._topic(msg.RETAKE_REST)
            topic = Topic(self._participant, name, cls, qos=qos)
            listener = Listener(on_data_available=self._retake_rest)
            readers.append(DataReader(self._participant, topic, qos, listener))
            self._entities += [readers[-1], topic]
        self.graph = RosGraph(
            self._participant,
            self.namespace,
            {DDS_TOPIC_PREFIX + self._topic(n): self._topic(n) for n in self._writers},
            [writer for writer, _cls in self._writers.values()],
            readers,
        )
        self._entities = [*self.graph.entities(), *self._entities]
        super().__init__(max_age_s=max_age_s, queue_size=queue_size)

    def _topic(self, name: str) -> str:
        return msg.topic(self.namespace, name)

    @property
    def retake_topic(self) -> str:
        """The ROS 2 topic a robot writes to for a new rest reference."""
        return self._topic(msg.RETAKE_REST)

    def topics(self) -> dict[str, str]:
        """ROS 2 topic name -> ROS 2 type of everything this publisher writes."""
        return {self._topic(name): TOPIC_TYPES[name] for name in self._writers}

    def subscribers(self) -> dict[str, int]:
        """ROS 2 topic name -> how many subscriptions (any node, any vendor) match it now."""
        return {
            self._topic(name): len(writer.get_matched_subscriptions())
            for name, (writer, _cls) in self._writers.items()
        }

    def _retake_rest(self, reader: Any) -> None:
        """A message on the retake_rest topic: ask for a new rest reference."""
        from cyclonedds.internal import InvalidSample

        try:
            samples = [s for s in reader.take(N=HISTORY_DEPTH) if not isinstance(s, InvalidSample)]
        except Exception:  # the reader is being deleted
            return
        if not samples:
            return
        self.retake_requests += len(samples)
        logger.info("ros2: a new rest reference asked for on %s", self.retake_topic)
        try:
            self.on_retake_rest()
        except BeadSightError as e:
            logger.warning("ros2: %s: %s", self.retake_topic, e)

    def _write(self, name: str, message: dict[str, Any]) -> None:
        writer, cls = self._writers[name]
        writer.write(build_struct(cls, message))

    def publish(self, update: Any) -> None:
        r = update.reading
        t = float(r.timestamp_s)
        self._write(msg.PRESSURE, msg.image_message(r.pressure_kpa, t))
        self._write(msg.FORCE, msg.wrench_message(r.force_n, t))
        cop = np.asarray(r.cop_mm, dtype=np.float64).reshape(2)
        if np.all(np.isfinite(cop)):
            self._write(msg.COP, msg.point_message(cop, t))
        self._write(msg.CONTACT_AREA, msg.area_message(r.contact_area_mm2, t))
        if np.isfinite(update.reference_force_n):
            self._write(msg.REFERENCE_FORCE, msg.wrench_message(update.reference_force_n, t))
        if self.camera:
            self._write(msg.CAMERA, msg.camera_message(update.frame_rgb, t))

    def publish_health(self, report: dict[str, Any]) -> None:
        self._write(msg.HEALTH, msg.diagnostics_message(report))

    def close(self) -> None:
        """Delete the writers, topics and participant now (Cyclone would on collection);
        deleting a writer first lets reliable readers acknowledge what it wrote."""
        self.graph.close()
        self._writers.clear()
        entities, self._entities = self._entities, []
        participant, self._participant = self._participant, None
        for entity in [*entities, participant]:
            if entity is not None:
                entity.__del__()  # dds_delete; idempotent (Cyclone tracks deleted entities)
