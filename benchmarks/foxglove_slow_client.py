"""Reading age at a slow Foxglove client (issue 27, item 3): the shipped sim model on the
simulator at 30 fps with ``FoxgloveServer``; a ``websockets`` client subscribed to every
channel reads one message every 0.1 s on the calling thread, and notes each message's age
(capture time -> the moment the client reads it).

    PYTHONPATH=src .venv/bin/python benchmarks/foxglove_slow_client.py [--seconds 6]

Rows: the client's WebSocket queue (``max_queue``) and receive buffer (``SO_RCVBUF``).
Prints one line per row, then a JSON list last.
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
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


def run(max_queue: int | str | None, rcvbuf: int, seconds: float, period_s: float) -> dict:
    sensor = LiveSensor(None, "sim", LiveSettings(backend="torch", precision="fp32"))
    sensor.open()
    server = FoxgloveServer(sensor.geometry, port=0)
    sensor.add_listener(server)
    sock = socket.socket()
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.connect(("127.0.0.1", server.port))
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
    args = parser.parse_args()
    print(cpu_summary())
    rows = []
    for max_queue, rcvbuf in ROWS:
        rows.append(run(max_queue, rcvbuf, args.seconds, args.period))
        print(rows[-1], flush=True)
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
