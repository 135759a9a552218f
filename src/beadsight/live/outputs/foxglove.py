"""Live readings in Foxglove (app or web): ``beadsight live --foxglove``.

Serves the Foxglove WebSocket protocol (:mod:`~beadsight.live.outputs.foxglove_ws`: local
origins only by default, a few clients, one reading in flight per client), with messages
encoded by ``foxglove-sdk`` (``pip install 'beadsight[ros]'``); per reading (channel names follow :mod:`beadsight.live.ros.messages`):

=================================  ====================  ===========================================
channel                            schema                content
=================================  ====================  ===========================================
``/beadsight/camera``              ``foxglove.RawImage``  the model-input frame, ``rgb8``
``/beadsight/pressure``            ``foxglove.Grid``      the map in kPa (field ``pressure_kpa``,
                                                         float32) in the ``beadsight`` frame, metres
``/beadsight/pressure_image``      ``foxglove.RawImage``  the map colour-mapped, 0..max_kpa (the live
                                                         viewer's scale), ``rgb8``
``/beadsight/reading``             JSON                   force_n, cop_m {x, y}, contact_area_m2,
                                                         has_contact, reference_force_n
``/beadsight/health``              JSON                   the health state (ok, drifting, recalibrate),
                                                         its message and figures, the sensor's state
=================================  ====================  ===========================================

Open Foxglove, connect to ``ws://HOST:PORT`` and import ``docs/foxglove-layout.json``.
Logging runs on its own thread (a slow client never slows sensing).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.errors import BeadSightError
from beadsight.live.config import (
    DEFAULT_HOST,
    MAX_AGE_S,
    check_count,
    check_namespace,
    check_port,
    check_positive,
)
from beadsight.live.config import FOXGLOVE_PORT as DEFAULT_PORT
from beadsight.live.config import VIEWER_MAX_KPA as DEFAULT_MAX_KPA
from beadsight.live.outputs.base import DEFAULT_QUEUE_SIZE, OutputListener
from beadsight.live.outputs.colormap import colormap_bgr, colour_indices
from beadsight.live.outputs.foxglove_ws import MAX_CLIENTS, ChannelSpec, FoxgloveWebSocket
from beadsight.live.ros import messages as msg

PRESSURE_IMAGE = "pressure_image"
READING = "reading"

READING_SCHEMA = {
    "type": "object",
    "properties": {
        "timestamp_s": {
            "type": "number",
            "description": "capture time of the newest frame, unix s",
        },
        "force_n": {"type": "number", "description": "total normal force, N"},
        "cop_m": {
            "type": ["object", "null"],
            "description": "centre of pressure in the beadsight frame, m (null without pressure)",
            "properties": {"x": {"type": "number"}, "y": {"type": "number"}},
        },
        "contact_area_m2": {"type": "number", "description": "contact area, m^2"},
        "has_contact": {"type": "boolean"},
        "reference_force_n": {
            "type": ["number", "null"],
            "description": "true force when the source knows it (the simulator), N",
        },
    },
}
HEALTH_SCHEMA = {
    "type": "object",
    "properties": {
        "timestamp_s": {"type": "number", "description": "when the report was made, unix s"},
        "state": {
            "type": ["string", "null"],
            "description": "health: ok, drifting or recalibrate (null: not tracked)",
        },
        "message": {"type": "string", "description": "what the health state means, what to do"},
        "figures": {"type": "object", "description": "the figures behind the health state"},
        "sensor_state": {"type": "string", "description": "the sensor's state (ok, no_signal...)"},
        "sensor_message": {"type": "string"},
        "sensor_since_s": {"type": ["number", "null"], "description": "since when, unix s"},
    },
}
HEALTH_STATUS_ID = "beadsight-health"  # the Foxglove app's problem entry for poor health
READING_SCHEMA_NAME, HEALTH_SCHEMA_NAME = "beadsight.Reading", "beadsight.Health"


def require_foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise BeadSightError(
            "--foxglove needs the Foxglove SDK (the 'foxglove-sdk' package): "
            "pip install 'beadsight[ros]'"
        ) from None
    try:
        import websockets  # noqa: F401
    except ImportError:
        raise BeadSightError(
            "--foxglove needs the 'websockets' package: pip install 'beadsight[ros]'"
        ) from None
    return foxglove


def _check(port: int, max_kpa: float, namespace: str) -> None:
    check_port(port, "Foxglove port")
    check_positive(max_kpa, "Foxglove max_kpa", "kPa")
    check_namespace(namespace)


def _timestamp(t_s: float) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(*msg.stamp(t_s))


def _channels(namespace: str) -> list[ChannelSpec]:
    """The advertised channels, in the order of :data:`CAMERA_ID` ... :data:`HEALTH_ID`."""
    from foxglove.messages import Grid, RawImage

    def typed(name: str, message: Any) -> ChannelSpec:
        schema = message.get_schema()
        return ChannelSpec(
            msg.topic(namespace, name), "protobuf", schema.name, schema.encoding, schema.data
        )

    def json_channel(name: str, schema_name: str, schema: dict) -> ChannelSpec:
        text = json.dumps(schema).encode()
        return ChannelSpec(msg.topic(namespace, name), "json", schema_name, "jsonschema", text)

    return [
        typed(msg.CAMERA, RawImage),
        typed(msg.PRESSURE, Grid),
        typed(PRESSURE_IMAGE, RawImage),
        json_channel(READING, READING_SCHEMA_NAME, READING_SCHEMA),
        json_channel(msg.HEALTH, HEALTH_SCHEMA_NAME, HEALTH_SCHEMA),
    ]


CAMERA_ID, PRESSURE_ID, PRESSURE_IMAGE_ID, READING_ID, HEALTH_ID = range(1, 6)


class FoxgloveServer(OutputListener):
    """Serves live updates to Foxglove over WebSocket (a ``LiveListener``).

    geometry: the model's sensor geometry (map size and mm per pixel).
    host, port: where the server listens (port 0: any free port, see :attr:`port`).
    max_kpa: top of the colour scale of ``pressure_image``.
    max_age_s, queue_size: the slow-client rule (:class:`~beadsight.live.outputs.base.OutputListener`),
    applied again per client when its turn comes (:mod:`~beadsight.live.outputs.foxglove_ws`:
    one reading in flight per client).
    allowed_origins: browser origins accepted beside local pages (``--foxglove-allow-origin``).
    max_clients: clients served at once (``--foxglove-max-clients``).
    """

    name = "foxglove"

    def __init__(
        self,
        geometry: SensorGeometry,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        namespace: str = msg.DEFAULT_NAMESPACE,
        max_kpa: float = DEFAULT_MAX_KPA,
        *,
        max_age_s: float = MAX_AGE_S,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        allowed_origins: tuple[str, ...] = (),
        max_clients: int = MAX_CLIENTS,
    ):
        require_foxglove()
        from foxglove.messages import PackedElementField, PackedElementFieldNumericType

        _check(port, max_kpa, namespace)
        check_count(max_clients, "Foxglove max_clients")
        self.geometry, self.max_kpa = geometry, max_kpa
        self._lut_rgb = colormap_bgr()[:, ::-1].copy()
        self._field = PackedElementField(
            name="pressure_kpa", offset=0, type=PackedElementFieldNumericType.Float32
        )
        self._channels = _channels(namespace)
        self._server = FoxgloveWebSocket(
            "beadsight",
            host,
            port,
            self._channels,
            allowed_origins=allowed_origins,
            max_clients=max_clients,
            max_age_s=max_age_s,
        )
        self.host, self.port = host, self._server.port
        self._status_shown = False  # a poor-health status is up in the clients
        super().__init__(max_age_s=max_age_s, queue_size=queue_size)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def topics(self) -> list[str]:
        return [c.topic for c in self._channels]

    def subscribers(self) -> dict[str, int]:
        """Topic -> how many clients are subscribed to it now."""
        return self._server.subscribers()

    def clients(self) -> int:
        """Clients connected now."""
        return self._server.clients()

    @property
    def client_skipped(self) -> int:
        """Readings not sent to a client because it had not read the one before (summed
        over the clients), or that were too old when its turn came."""
        return self._server.skipped()

    def _raw_image(self, rgb: np.ndarray, t_s: float) -> Any:
        from foxglove.messages import RawImage

        h, w, _ = rgb.shape
        return RawImage(
            timestamp=_timestamp(t_s),
            frame_id=msg.FRAME_ID,
            width=w,
            height=h,
            encoding="rgb8",
            step=3 * w,
            data=np.ascontiguousarray(rgb).tobytes(),
        )

    def _grid(self, kpa: np.ndarray, t_s: float) -> Any:
        """The map as a grid in the beadsight frame: row 0 is +y, column 0 is +x, so the
        grid's origin is the (+x, +y) corner, turned half a turn about z."""
        from foxglove.messages import Grid, Pose, Quaternion, Vector2, Vector3

        h, w = kpa.shape
        cell_m = self.geometry.sensor_size_mm / w * msg.M_PER_MM
        half = w * cell_m / 2
        return Grid(
            timestamp=_timestamp(t_s),
            frame_id=msg.FRAME_ID,
            pose=Pose(
                position=Vector3(x=half, y=half, z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=1.0, w=0.0),
            ),
            column_count=w,
            cell_size=Vector2(x=cell_m, y=cell_m),
            row_stride=4 * w,
            cell_stride=4,
            fields=[self._field],
            data=np.ascontiguousarray(kpa, dtype="<f4").tobytes(),
        )

    def publish(self, update: Any) -> None:
        r = update.reading
        t = float(r.timestamp_s)
        t_ns = msg.unix_ns(t)
        index = colour_indices(r.pressure_kpa, self.max_kpa, len(self._lut_rgb))
        cop = np.asarray(r.cop_mm, dtype=float).reshape(2)
        reading = {
            "timestamp_s": t,
            "force_n": float(r.force_n),
            "cop_m": (
                {"x": cop[0] * msg.M_PER_MM, "y": cop[1] * msg.M_PER_MM}
                if np.all(np.isfinite(cop))
                else None
            ),
            "contact_area_m2": float(r.contact_area_mm2) * msg.M2_PER_MM2,
            "has_contact": bool(r.has_contact),
            "reference_force_n": msg.finite_or_none(update.reference_force_n),
        }
        messages = [
            (CAMERA_ID, t_ns, self._raw_image(update.frame_rgb, t).encode()),
            (PRESSURE_ID, t_ns, self._grid(r.pressure_kpa, t).encode()),
            (PRESSURE_IMAGE_ID, t_ns, self._raw_image(self._lut_rgb[index], t).encode()),
            (READING_ID, t_ns, json.dumps(reading).encode()),
        ]
        self._server.log_reading(self.arrived_s, messages)

    def publish_health(self, report: dict[str, Any]) -> None:
        """The report on ``/beadsight/health``; poor health also shows as a problem in the
        Foxglove app (warning: drifting, error: recalibrate)."""
        t_ns = msg.unix_ns(report["timestamp_s"])
        self._server.log(HEALTH_ID, t_ns, json.dumps(report).encode())
        level = {"drifting": "warning", "recalibrate": "error"}.get(report["state"])
        if level is not None:
            text = f"beadsight health: {report['state']}. {report['message']}".strip()
            self._server.publish_status(text, level, HEALTH_STATUS_ID)
        elif self._status_shown:
            self._server.remove_status([HEALTH_STATUS_ID])
        self._status_shown = level is not None

    def close(self) -> None:
        self._server.stop()
