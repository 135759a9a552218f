"""Foxglove live (``beadsight live --foxglove``), watched by a WebSocket client written from
the Foxglove protocol (``foxglove.sdk.v1``: JSON ops as text frames, messages as binary
frames), which decodes the typed messages with the protobuf schemas the server advertises."""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import signal
import struct
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import websockets.sync.client as websockets_sync
from helpers.browser import Beadsight
from helpers.live import (
    BACKEND,
    press_frames,
    tiny_model,
    wait_until,
)
from helpers.publish import HEALTH_STATES, HealthTagger, PacedSource, live_without
from websockets.exceptions import ConnectionClosedOK

from beadsight.cli import main
from beadsight.live.ros import messages as msg
from beadsight.live.sensor import LiveSensor

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"
SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01  # binary opcode: u32 subscription id, u64 log time (ns), payload
NS = msg.DEFAULT_NAMESPACE
CHANNELS = {  # topic -> (message encoding, schema name, schema encoding)
    f"{NS}/camera": ("protobuf", "foxglove.RawImage", "protobuf"),
    f"{NS}/pressure": ("protobuf", "foxglove.Grid", "protobuf"),
    f"{NS}/pressure_image": ("protobuf", "foxglove.RawImage", "protobuf"),
    f"{NS}/reading": ("json", "beadsight.Reading", "jsonschema"),
    f"{NS}/health": ("json", "beadsight.Health", "jsonschema"),
}


class FoxgloveClient:
    """Connects, reads the server's advertisement, subscribes to every channel and decodes
    what arrives (protobuf with the advertised FileDescriptorSet, JSON as JSON)."""

    def __init__(self, ws):
        self.ws = ws
        assert ws.subprotocol == SUBPROTOCOL
        self.info = self._op("serverInfo")
        self.channels = {c["topic"]: c for c in self._op("advertise")["channels"]}
        self.ops: list[dict] = []  # text ops after the advertisement (status, ...)
        self._topic_of: dict[int, str] = {}
        self._decoders: dict[str, object] = {}

    def _op(self, name: str) -> dict:
        op = json.loads(self.ws.recv(timeout=10))
        assert op["op"] == name, op
        return op

    def subscribe_all(self) -> None:
        subs = [{"id": i, "channelId": c["id"]} for i, c in enumerate(self.channels.values())]
        self._topic_of = {i: topic for i, topic in enumerate(self.channels)}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def decode(self, topic: str, payload: bytes):
        channel = self.channels[topic]
        if channel["encoding"] == "json":
            return json.loads(payload)
        if topic not in self._decoders:
            from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

            files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
            pool = descriptor_pool.DescriptorPool()
            for f in files.file:
                pool.Add(f)
            descriptor = pool.FindMessageTypeByName(channel["schemaName"])
            self._decoders[topic] = message_factory.GetMessageClass(descriptor)
        return self._decoders[topic].FromString(payload)

    def receive(self, until, timeout_s: float = 30, to_close: bool = False) -> dict[str, list]:
        """(log time ns, decoded message) by topic until ``until(got)`` is true, or with
        ``to_close`` until the server closes the connection normally."""
        got: dict[str, list] = {}
        deadline = time.monotonic() + timeout_s
        while not until(got):
            assert time.monotonic() < deadline, (
                f"timed out; got { ({k: len(v) for k, v in got.items()}) }"
            )
            try:
                frame = self.ws.recv(timeout=deadline - time.monotonic())
            except ConnectionClosedOK:
                if to_close:
                    return got
                raise
            if isinstance(frame, str):
                self.ops.append(json.loads(frame))
                continue
            assert frame[0] == MESSAGE_DATA
            sub, log_ns = struct.unpack_from("<IQ", frame, 1)
            topic = self._topic_of[sub]
            got.setdefault(topic, []).append((log_ns, self.decode(topic, frame[13:])))
        return got


@contextlib.contextmanager
def foxglove_client(url: str):
    with websockets_sync.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=10) as ws:
        yield FoxgloveClient(ws)


def grid_force_and_cop(grid) -> tuple[float, np.ndarray]:
    """Total force (N) and centre of pressure (m, beadsight frame) of a foxglove.Grid of kPa,
    placed by its own pose and cell size."""
    field = grid.fields[0]
    assert (field.name, field.offset, grid.cell_stride) == ("pressure_kpa", 0, 4)
    cols = grid.column_count
    kpa = np.frombuffer(grid.data, "<f4").reshape(-1, grid.row_stride // 4)[:, :cols]
    rows = kpa.shape[0]
    q = grid.pose.orientation
    assert (q.x, q.y, q.z, q.w) == (0, 0, 1, 0)  # half a turn about z: grid +x is -x
    x = grid.pose.position.x - (np.arange(cols) + 0.5) * grid.cell_size.x
    y = grid.pose.position.y - (np.arange(rows) + 0.5) * grid.cell_size.y
    p = np.clip(kpa.astype(np.float64), 0, None)
    force = p.sum() * 1e3 * grid.cell_size.x * grid.cell_size.y
    cop = np.array([(p.sum(0) * x).sum(), (p.sum(1) * y).sum()]) / p.sum()
    return force, cop


def _ns(timestamp) -> int:
    return timestamp.seconds * 10**9 + timestamp.nanos


@pytest.mark.slow
def test_beadsight_live_foxglove_serves_every_channel():
    """`beadsight live --source sim --foxglove`: a client sees the advertised channels and
    receives each; the Grid, placed by its pose, gives the reading's force and CoP."""
    # seed 75: the press it waits for comes from about the 10th reading (seed 0: the 55th)
    run = Beadsight(
        *("live", "--source", "sim", "--seed", "75", "--no-viewer", "--backend", "torch"),
        *("--foxglove", "--foxglove-port", "0", "--frames", "600"),
    )
    try:
        url = run.wait_line(r"foxglove: (ws://\S+)", 60).group(1)

        def pressed(got) -> bool:  # every channel, and a reading of a press
            readings = [m for _, m in got.get(f"{NS}/reading", [])]
            return len(got) == len(CHANNELS) and any(r["has_contact"] for r in readings)

        with foxglove_client(url) as client:
            assert client.info["name"] == "beadsight"
            assert {
                t: (c["encoding"], c["schemaName"], c["schemaEncoding"])
                for t, c in client.channels.items()
            } == CHANNELS
            client.subscribe_all()
            got = client.receive(pressed, timeout_s=60)
        run.proc.send_signal(signal.SIGINT)
        assert run.proc.wait(30) == 0, run.rest()
    finally:
        if run.proc.poll() is None:
            run.proc.kill()
    grids = {_ns(g.timestamp): (t, g) for t, g in got[f"{NS}/pressure"]}
    reading = next(r for _, r in got[f"{NS}/reading"] if r["has_contact"])
    t_ns = round(Fraction(reading["timestamp_s"]) * 10**9)  # the capture time, exactly
    log_ns, grid = grids[t_ns]
    assert log_ns == t_ns and grid.frame_id == msg.FRAME_ID
    assert grid.column_count == 64 and grid.cell_size.x == pytest.approx(41e-3 / 64)
    force, cop = grid_force_and_cop(grid)
    assert force == pytest.approx(reading["force_n"], rel=1e-4)
    assert cop == pytest.approx([reading["cop_m"]["x"], reading["cop_m"]["y"]], rel=1e-4)
    assert reading["contact_area_m2"] > 0
    assert reading["reference_force_n"] >= 0  # the simulator knows the true force
    for topic in (f"{NS}/camera", f"{NS}/pressure_image"):
        image = got[topic][-1][1]
        assert (image.encoding, image.width, image.height, image.step) == ("rgb8", 64, 64, 192)
        assert len(image.data) == 64 * 64 * 3 and image.frame_id == msg.FRAME_ID
    health = got[f"{NS}/health"][-1][1]
    assert health["sensor_state"] == "ok"
    assert health["state"] in ("unknown", "ok")  # tracked: no reference yet, or at rest


def test_health_reaches_the_client_and_the_app_status(tmp_path):
    """Health states on /beadsight/health as they change, and poor health as a status
    (the Foxglove app's problems list): warning when drifting, error to recalibrate."""
    from beadsight.live.outputs.foxglove import HEALTH_STATUS_ID, FoxgloveServer

    frames, _ = press_frames(presses=3, per_press=30)
    sensor = LiveSensor(tiny_model(), PacedSource(frames, fps=60.0), **BACKEND)
    sensor.open()
    server = FoxgloveServer(sensor.geometry, port=0, queue_size=64)

    readings = len(frames) - sensor.model.span + 1

    with foxglove_client(server.url) as client:
        client.subscribe_all()
        wait_until(lambda: all(server.subscribers().values()), 10, "subscriptions")
        sensor.add_listener(HealthTagger(server, total=readings))
        sensor.start()
        # statuses travel apart from messages, and health apart from readings (paced per
        # client): take everything until the server closes, at the end of the stream
        got = client.receive(lambda got: False, timeout_s=30, to_close=True)
    sensor.stop()
    server.finish()
    reports = [m for _, m in got[f"{NS}/health"]]
    states = [k for k, _ in itertools.groupby(m["state"] for m in reports)]
    assert states == [None, *HEALTH_STATES]  # None: warming up, no reading (no health) yet
    drifting = next(m for m in reports if m["state"] == "drifting")
    assert drifting["message"] == "drifting: see docs/live.md"
    assert drifting["figures"]["force_offset_n"] is None and drifting["figures"]["n"] == 3
    assert drifting["sensor_state"] == "ok"
    statuses = [(op["level"], op["id"]) for op in client.ops if op["op"] == "status"]
    assert [k for k, _ in itertools.groupby(statuses)] == [
        (1, HEALTH_STATUS_ID),
        (2, HEALTH_STATUS_ID),
    ]
    assert server.published == readings
    # a client that falls a frame behind gets the newer reading in place of the older one
    # (counted in skipped, per channel); none is lost uncounted, none is sent twice
    stamps = [log_ns for log_ns, _ in got[f"{NS}/reading"]]
    assert stamps == sorted(set(stamps))
    assert readings - server.client_skipped <= len(stamps) <= readings


def test_layout_shows_our_channels():
    """docs/foxglove-layout.json: every panel placed, and every topic and field it shows is
    one the server publishes (camera, pressure map and grid, force plot, health)."""
    from beadsight.live.outputs.foxglove import HEALTH_SCHEMA, READING_SCHEMA

    layout = json.loads(LAYOUT.read_text())
    config = layout["configById"]

    def leaves(node) -> list[str]:
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(config)
    fields = {f"{NS}/reading": READING_SCHEMA, f"{NS}/health": HEALTH_SCHEMA}

    def check_path(path: str) -> None:
        topic = next(t for t in fields if path.startswith(t + "."))
        schema = fields[topic]
        for name in path[len(topic) + 1 :].split("."):
            assert name in schema["properties"], f"{path}: no field {name!r}"
            schema = schema["properties"][name]

    images = {config[k]["imageMode"]["imageTopic"] for k in config if k.startswith("Image!")}
    assert images == {f"{NS}/camera", f"{NS}/pressure_image"}
    grid_topics = {t for k in config if k.startswith("3D!") for t in config[k]["topics"]}
    assert grid_topics == {f"{NS}/pressure"}
    plotted = [p["value"] for k in config if k.startswith("Plot!") for p in config[k]["paths"]]
    assert f"{NS}/reading.force_n" in plotted
    for path in plotted + [config["Indicator!health"]["path"]]:
        check_path(path)
    rules = config["Indicator!health"]["rules"]
    assert [r["rawValue"] for r in rules] == list(HEALTH_STATES)
    assert config["RawMessages!health"]["topicPath"] == f"{NS}/health"
    assert set(images | grid_topics | {f"{NS}/reading", f"{NS}/health"}) == set(CHANNELS)


def test_foxglove_errors_are_one_line(capsys):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(
            ["live", "--source", "sim", "--no-viewer", "--backend", "torch"]
            + ["--foxglove", "--foxglove-port", str(port), "--frames", "1"]
        )
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1
    assert f"Foxglove server on 127.0.0.1:{port}" in err
    assert main(["live", "--no-viewer", "--foxglove", "--foxglove-port", "70000"]) == 1
    assert "Foxglove port 70000: expected 0..65535" in capsys.readouterr().err


def test_missing_foxglove_sdk_names_the_extra(monkeypatch, capsys):
    assert live_without(monkeypatch, capsys, "foxglove", "--foxglove") == [
        "beadsight live: error: --foxglove needs the Foxglove SDK (the 'foxglove-sdk' "
        "package): pip install 'beadsight[ros]'"
    ]
