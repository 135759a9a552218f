"""Sensing rate with idle viewer connections: does a crowd of `/events` clients slow sensing?

Target: `beadsight live --source sim` keeps its 30 Hz with 200 idle `/events` connections
open (connections that sent their request and then never read).

    .venv/bin/python benchmarks/viewer_idle_clients.py                 # 0 and 200 clients
    .venv/bin/python benchmarks/viewer_idle_clients.py --clients 0 50 200 --seconds 10
    .venv/bin/python benchmarks/viewer_idle_clients.py --max-clients 200   # serve them all

For each client count the script runs a LiveSensor on the simulator (30 fps, a 64 px
width-8 model with random weights) with the web viewer, opens that many idle `/events`
connections, waits --settle seconds, then counts readings for --seconds. It prints the
achieved sensing rate, how many connections the viewer answered with 200 (served) or 503
(refused: over its connection cap), and the CPU model.
"""

from __future__ import annotations

import argparse
import socket
import time

from beadsight.checkpoint import PressureModel
from beadsight.inference.machine import cpu_summary
from beadsight.live.bench import random_model
from beadsight.live.outputs.viewer.server import ViewerServer
from beadsight.live.sensor import LiveSensor
from beadsight.live.settings import LiveSettings

REQUEST = b"GET /events HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nAccept: text/event-stream\r\n\r\n"


def tiny_model() -> PressureModel:
    """The 64 px, width-8 model of the live tests, random weights (same cost as trained)."""
    return random_model(image_size=64, frames=15, width=8)


def open_idle(port: int, count: int) -> list[socket.socket]:
    """``count`` connections that ask for /events and then never read."""
    socks = []
    for _ in range(count):
        sock = socket.create_connection(("127.0.0.1", port))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.sendall(REQUEST % port)
        socks.append(sock)
    return socks


def answers(socks: list[socket.socket]) -> dict[str, int]:
    """How the viewer answered each connection: status code, or 'none' (no answer yet)."""
    out: dict[str, int] = {}
    for sock in socks:
        sock.settimeout(0.5)
        try:
            first = sock.recv(64).split(b"\r\n", 1)[0]
            code = first.split()[1].decode() if first else "closed"
        except (TimeoutError, OSError, IndexError):
            code = "none"
        out[code] = out.get(code, 0) + 1
    return out


def run(model: PressureModel, clients: int, args: argparse.Namespace) -> None:
    seconds, settle, fps = args.seconds, args.settle, args.fps
    options = {} if args.max_clients is None else {"max_clients": args.max_clients}
    with LiveSensor(model, "sim", LiveSettings("torch", "fp32", source_fps=fps)) as sensor:
        with ViewerServer(sensor, port=0, **options) as viewer:
            socks = open_idle(viewer.port, clients)
            try:
                time.sleep(settle)
                n0, t0 = sensor.stats().readings, time.monotonic()
                time.sleep(seconds)
                n1, t1 = sensor.stats().readings, time.monotonic()
                codes = answers(socks)
            finally:
                for sock in socks:
                    sock.close()
    rate = (n1 - n0) / (t1 - t0)
    print(
        f"{clients:4d} idle /events connections: sensing {rate:5.1f} readings/s "
        f"(source {fps:g} fps); viewer answers: {codes or '-'}",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, nargs="+", default=[0, 200])
    parser.add_argument("--seconds", type=float, default=8.0, help="measuring time per run")
    parser.add_argument("--settle", type=float, default=3.0, help="wait before measuring")
    parser.add_argument("--fps", type=float, default=30.0, help="simulator rate")
    parser.add_argument(
        "--max-clients",
        type=int,
        default=None,
        help="the viewer's connection cap (default: its own)",
    )
    args = parser.parse_args()
    print(cpu_summary())
    model = tiny_model()
    for clients in args.clients:
        run(model, clients, args)


if __name__ == "__main__":
    main()
