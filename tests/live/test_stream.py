"""The TCP readings stream, read by the documented client as a separate process."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers.live import (
    BACKEND,
    SPAN,
    TINY,
    TORCH,
    ScriptedSource,
    press_frames,
    wait_until,
)

from beadsight.config import SensorGeometry
from beadsight.errors import BeadSightError
from beadsight.live.listeners import LiveStatus
from beadsight.live.sensor import LiveSensor
from beadsight.live.stream import StreamServer, encode_reading

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads

CLIENT = Path(__file__).resolve().parents[2] / "examples" / "stream_client.py"


def read_message(stream) -> tuple[dict, bytes]:
    header = json.loads(stream.readline())
    return header, stream.read(header["payload_bytes"])


def test_client_example_does_not_import_beadsight():
    source = CLIENT.read_text()
    assert "beadsight" not in "".join(
        line for line in source.splitlines() if line.lstrip().startswith(("import", "from"))
    )


def test_separate_client_process_receives_the_readings(model):
    frames, force = press_frames(presses=2, per_press=30)
    source = ScriptedSource(frames, forces=force, stall_after=SPAN - 1)
    published = []
    sensor = LiveSensor(model, source, **BACKEND)
    sensor.on_reading(published.append)
    with StreamServer(TINY, port=0) as server, sensor:
        sensor.add_listener(server)
        client = subprocess.Popen(
            [sys.executable, str(CLIENT), "--port", str(server.port), "--count", "20"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_until(lambda: server.client_count == 1, 30, "the client to connect")
            source.release.set()  # frames flow only once the client listens
            out, err = client.communicate(timeout=60)
        finally:
            client.kill()
    assert client.returncode == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    assert len(lines) == 20
    by_index = {r.frame_index: r for r in published}
    for line in lines:
        reading = by_index[line["frame_index"]]
        assert line["timestamp_s"] == reading.timestamp_s
        assert line["force_n"] == pytest.approx(reading.force_n, rel=1e-9)
        # the map's bytes are the reading's map: its integral is the force
        assert line["map_force_n"] == pytest.approx(reading.force_n, rel=1e-5)
        assert line["peak_kpa"] == pytest.approx(float(reading.pressure_kpa.max()), rel=1e-6)
        if line["cop_mm"] is None:
            assert not np.all(np.isfinite(reading.cop_mm))
        else:
            np.testing.assert_allclose(line["cop_mm"], reading.cop_mm, rtol=1e-9)
    indices = [line["frame_index"] for line in lines]
    assert indices[0] == min(by_index) and np.all(np.diff(indices) > 0)
    assert "status: ok" in err  # status messages reach the client


def test_message_format_header_line_then_little_endian_map():
    class Update:
        reading = type("R", (), {})()
        latency_s = 0.012
        reference_force_n = math.nan

    r = Update.reading
    r.pressure_kpa = np.arange(12, dtype=np.float32).reshape(3, 4)
    r.force_n, r.cop_mm, r.has_contact = 1.5, np.array([np.nan, np.nan]), False
    r.contact_area_mm2, r.timestamp_s, r.latency_s = 0.0, 1.7e9 + 0.25, 0.004
    r.frame_index, r.dropped_frames = 42, 1
    message = encode_reading(Update(), seq=7, skipped=2)
    head, _, payload = message.partition(b"\n")
    header = json.loads(head)
    assert header["type"] == "reading" and header["seq"] == 7 and header["skipped"] == 2
    assert header["cop_mm"] is None and header["reference_force_n"] is None
    assert (header["height"], header["width"], header["dtype"]) == (3, 4, "<f4")
    assert header["payload_bytes"] == len(payload) == 48
    np.testing.assert_array_equal(np.frombuffer(payload, "<f4").reshape(3, 4), r.pressure_kpa)


def test_hello_and_status_messages_and_clean_close():
    with StreamServer(TINY, port=0) as server:
        server.status(LiveStatus("no_signal", "camera 0 unplugged", 1.0))
        with socket.create_connection((server.host, server.port)) as sock:
            stream = sock.makefile("rb")
            hello, payload = read_message(stream)
            assert hello["type"] == "hello" and hello["version"] == 1 and payload == b""
            assert hello["mm_per_px"] == pytest.approx(TINY.mm_per_px)
            status, _ = read_message(stream)  # late joiners get the current status
            assert status == {
                "type": "status",
                "seq": 0,  # no reading yet
                "skipped": 0,
                "state": "no_signal",
                "message": "camera 0 unplugged",
                "since_s": 1.0,
                "payload_bytes": 0,
            }
            server.close()
            closed, _ = read_message(stream)
            assert closed["state"] == "closed"
            assert stream.readline() == b""  # then EOF


def test_client_that_never_reads_does_not_slow_the_sensor(model):
    frames, _ = press_frames(presses=4, per_press=30)
    with StreamServer(TINY, port=0) as server:
        with socket.create_connection((server.host, server.port)) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            wait_until(lambda: server.client_count == 1, 10, "client")
            with LiveSensor(model, ScriptedSource(frames), **BACKEND) as sensor:
                sensor.add_listener(server)
                assert sensor.wait(60)
            # all 120 - 14 readings were produced although nobody read ~28 MB of maps
            assert sensor.stats().readings == len(frames) - SPAN + 1


def test_port_in_use_is_a_clear_error():
    with StreamServer(TINY, port=0) as server:
        with pytest.raises(BeadSightError, match=f"{server.port}.*--stream-port"):
            StreamServer(TINY, port=server.port)


def _reconciles(messages: list[dict]) -> None:
    """For consecutive reading/status messages a, b of one client:
    b.seq - a.seq - (1 if b is a reading else 0) == b.skipped."""
    numbered = [m for m in messages if m["type"] in ("reading", "status")]
    for a, b in zip(numbered, numbered[1:], strict=False):
        step = 1 if b["type"] == "reading" else 0
        assert b["seq"] - a["seq"] - step == b["skipped"], (a, b)


def test_slow_client_gets_fresh_readings_and_counts_the_skipped(model):
    """A separate client process reading 10 readings/s while the sensor runs at 30 Hz."""
    max_age_s, margin_s, interval_s = 0.5, 0.25, 0.1
    with (
        StreamServer(TINY, port=0, max_age_s=max_age_s) as server,
        LiveSensor(model, "sim", replace(TORCH, source_fps=30)) as sensor,
    ):
        sensor.add_listener(server)
        command = [
            sys.executable,
            str(CLIENT),
            "--port",
            str(server.port),
            "--count",
            "40",
            "--interval",
            str(interval_s),
        ]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
        rate = sensor.stats().rate_hz
    assert done.returncode == 0, done.stderr
    readings = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(readings) == 40
    ages = [r["age_s"] for r in readings]
    # today's server queued ~8 s of readings in socket buffers: ages grew without bound
    assert max(ages) <= max_age_s + margin_s, ages
    assert rate > 25, rate  # the sensor kept its 30 Hz
    skipped = [r["skipped"] for r in readings]
    assert sum(skipped[1:]) > len(readings)  # about 2 of every 3 readings were skipped
    _reconciles([{"type": "reading", **r} for r in readings])


class _Update:
    """A stand-in LiveUpdate with a size x size map (what StreamServer.push reads)."""

    def __init__(self, k: int, size: int):
        self.latency_s, self.reference_force_n = 0.01, math.nan
        r = self.reading = type("R", (), {})()
        r.pressure_kpa = np.full((size, size), float(k), np.float32)
        r.force_n, r.cop_mm, r.has_contact = float(k), np.array([0.0, 0.0]), True
        r.contact_area_mm2, r.timestamp_s, r.latency_s = 1.0, time.time(), 0.005
        r.frame_index, r.dropped_frames = k, 0


def test_readings_older_than_the_limit_are_never_sent():
    big = SensorGeometry(image_size_px=256)  # one message (256 KiB) outgrows the buffers
    with StreamServer(big, port=0, max_age_s=0.3) as server:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect((server.host, server.port))
        with sock, sock.makefile("rb") as stream:
            wait_until(lambda: server.client_count == 1, 10, "the client")
            server.push(_Update(1, 256))
            time.sleep(0.2)  # reading 1 is being sent: the sender waits for the client
            for k in range(2, 7):  # 2-4 are dropped at once (queue of 2), 5 and 6 wait
                server.push(_Update(k, 256))
            time.sleep(0.6)  # now 5 and 6 are older than 0.3 s
            got = [read_message(stream)[0] for _ in range(2)]  # hello, reading 1
            server.push(_Update(7, 256))  # fresh
            got.append(read_message(stream)[0])
    assert [m["type"] for m in got] == ["hello", "reading", "reading"]
    assert [m["seq"] for m in got[1:]] == [1, 7]  # 5 and 6 were never sent
    assert got[2]["skipped"] == 5
    _reconciles(got)


def test_every_client_gets_ended_and_closed():
    """Fast, slow and paused clients all receive the final statuses, and their counts add
    up, with reference-size maps (256x256: 256 KiB per reading) at 30 readings/s."""
    big = SensorGeometry(image_size_px=256)
    server = StreamServer(big, port=0)
    results: dict[str, list[dict]] = {}
    closing = threading.Event()

    def client(name: str, interval_s: float, paused: bool) -> None:
        sock = socket.create_connection((server.host, server.port))  # the system's buffers
        got = results.setdefault(name, [])
        with sock, sock.makefile("rb") as stream:
            if paused:  # reads nothing until 1.2 s after the server began to close
                closing.wait(60)
                time.sleep(1.2)
            while line := stream.readline():
                header = json.loads(line)
                stream.read(header["payload_bytes"])
                got.append(header)
                if header["type"] == "reading":
                    time.sleep(interval_s)

    threads = [
        threading.Thread(target=client, args=args)
        for args in (("fast", 0.0, False), ("slow", 0.1, False), ("paused", 0.0, True))
    ]
    for t in threads:
        t.start()
    produced = 45
    try:
        wait_until(lambda: server.client_count == 3, 10, "3 clients")
        server.status(LiveStatus("ok", "sim", time.time()))
        for k in range(1, produced + 1):
            server.push(_Update(k, 256))
            time.sleep(1 / 30)
        server.status(LiveStatus("ended", "sim ended", time.time()))
    finally:
        closing.set()
        server.close()
        for t in threads:
            t.join(30)
    for name, got in results.items():
        states = [m["state"] for m in got if m["type"] == "status"]
        assert states[-2:] == ["ended", "closed"], (name, states)
        _reconciles(got)
        readings = [m for m in got if m["type"] == "reading"]
        assert got[-1]["seq"] == produced  # every reading is either received or counted
        assert len(readings) + sum(m["skipped"] for m in got if "skipped" in m) == produced, name
    assert sum(m["skipped"] for m in results["slow"] if "skipped" in m) > 0
