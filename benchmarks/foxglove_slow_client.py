"""Reading age at a slow Foxglove client (issue 27, item 3): the shipped sim model on the
simulator at 30 fps with ``FoxgloveServer``; a ``websockets`` client subscribed to every
channel reads one message every 0.1 s on the calling thread, and notes each message's age
(capture time -> the moment the client reads it).

    PYTHONPATH=src .venv/bin/python benchmarks/foxglove_slow_client.py [--seconds 6]
        [--period 0.1] [--rtt-ms 0]

``--period 0``: a client that reads as fast as it can (the Foxglove app). ``--rtt-ms``: the
client reaches the server through a relay that delays every byte by half that in each
direction, a network round trip.

Rows: the client's WebSocket queue (``max_queue``) and receive buffer (``SO_RCVBUF``).
Prints one line per row, then a JSON list last.
"""

from __future__ import annotations

import argparse
import json
import queue
import socket
import struct
import threading
import time

import numpy as np
from websockets.sync.client import connect

from beadsight.inference.machine import cpu_summary
from beadsight.live.outputs.foxglove import FoxgloveServer
from beadsight.live.sensor import LiveSensor
from beadsight.live.settings import LiveSettings

# (max_queue: "default" = websockets' own (16 frames), None = unbounded; SO_RCVBUF, 0: default)
ROWS = [("default", 0), (None, 0), (4, 0), (1, 0), (1, 16384)]
WARMUP_S = 1.0  # ages before this (after the first reading) are not counted


class DelayRelay:
    """One TCP connection relayed to ``127.0.0.1:port`` with every byte delayed by
    ``one_way_s`` in each direction: a link with that latency and no bandwidth limit."""

    def __init__(self, port: int, one_way_s: float):
        self.target, self.one_way_s = port, one_way_s
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        near, _ = self.listener.accept()
        far = socket.create_connection(("127.0.0.1", self.target))
        for end in (near, far):  # as the two ends do: no Nagle delay on small frames
            end.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for src, dst in ((near, far), (far, near)):
            q: queue.Queue = queue.Queue()
            threading.Thread(target=self._read, args=(src, q), daemon=True).start()
            threading.Thread(target=self._write, args=(dst, q), daemon=True).start()

    def _read(self, src: socket.socket, q: queue.Queue) -> None:
        try:
            while data := src.recv(65536):
                q.put((time.monotonic() + self.one_way_s, data))
        except OSError:
            pass
        q.put(None)

    def _write(self, dst: socket.socket, q: queue.Queue) -> None:
        try:
            while (item := q.get()) is not None:
                time.sleep(max(0.0, item[0] - time.monotonic()))
                dst.sendall(item[1])
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            pass


def run(
    max_queue: int | str | None, rcvbuf: int, seconds: float, period_s: float, rtt_s: float = 0
) -> dict:
    sensor = LiveSensor(None, "sim", LiveSettings(backend="torch", precision="fp32"))
    sensor.open()
    server = FoxgloveServer(sensor.geometry, port=0)
    sensor.add_listener(server)
    sock = socket.socket()
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    port = DelayRelay(server.port, rtt_s / 2).port if rtt_s > 0 else server.port
    sock.connect(("127.0.0.1", port))
    ages = []
    options = {"subprotocols": ["foxglove.sdk.v1"]}
    if max_queue != "default":
        options["max_queue"] = max_queue
    with connect(server.url, sock=sock, **options) as ws:
        json.loads(ws.recv(10))
        channels = json.loads(ws.recv(10))["channels"]
        subs = [{"id": i, "channelId": c["id"]} for i, c in enumerate(channels)]
        ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        sensor.start()
        while sensor.stats().readings < 30:
            time.sleep(0.05)
        start = time.monotonic()
        while time.monotonic() - start < seconds + WARMUP_S:
            frame = ws.recv(10)
            if isinstance(frame, bytes) and frame[0] == 0x01:
                log_ns = struct.unpack_from("<IQ", frame, 1)[1]
                if time.monotonic() - start > WARMUP_S:
                    ages.append(time.time() - log_ns / 1e9)
            time.sleep(period_s)
    sensor.stop()
    server.finish()
    p50, p95, top = np.percentile(ages, [50, 95, 100])
    return {
        "rtt_ms": round(rtt_s * 1000),
        "max_queue": max_queue,
        "so_rcvbuf": rcvbuf or "default",
        "messages": len(ages),
        "age_p50_s": round(float(p50), 3),
        "age_p95_s": round(float(p95), 3),
        "age_max_s": round(float(top), 3),
        "server_published": server.published,
        "server_skipped": server.skipped,
        "client_skipped_messages": server.client_skipped,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--period", type=float, default=0.1, help="s between client reads")
    parser.add_argument("--rtt-ms", type=float, default=0.0, help="network round trip, ms")
    args = parser.parse_args()
    print(cpu_summary())
    rows = []
    for max_queue, rcvbuf in ROWS:
        rows.append(run(max_queue, rcvbuf, args.seconds, args.period, args.rtt_ms / 1000))
        print(rows[-1], flush=True)
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
