"""Does publishing slow sensing? The live rate and latency without outputs and with ROS 2
(``--ros2``) and Foxglove (``--foxglove``) on, each with a consumer attached.

Target (issue 15): with both on, the shipped sim model keeps 30 Hz from the simulated
source and the p99 latency stays within 5 ms of the run without them.

    .venv/bin/python benchmarks/live_outputs.py                  # none, ros2, foxglove, both
    .venv/bin/python benchmarks/live_outputs.py --rows none both none both --seconds 20 --json

Each row runs a LiveSensor with the shipped sim model on the simulator paced at --fps for
--seconds after warm-up and prints readings/s, skipped frames and latency percentiles
(capture timestamp -> reading available, as `beadsight live` reports). ROS 2 rows attach
an independent subscriber in another process (tests/live/ros2_peer.py: best effort on the
images, reliable on the rest); Foxglove rows attach a WebSocket client in another process
subscribed to every channel. DDS stays on 127.0.0.1 (a loopback Cyclone config) unless
CYCLONEDDS_URI is set. Prints the CPU model, its cores and flags beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from beadsight.inference.machine import cpu_summary
from beadsight.live.sensor import LiveSensor
from beadsight.live.settings import LiveSettings

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "tests" / "live" / "ros2_peer.py"
ROWS = {
    "none": (False, False),
    "ros2": (True, False),
    "foxglove": (False, True),
    "both": (True, True),
}
DOMAIN = 97  # ROS domain of the benchmark
LOOPBACK = """<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any">
<General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
<AllowMulticast>false</AllowMulticast></General>
<Discovery><ParticipantIndex>auto</ParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers>
</Discovery></Domain></CycloneDDS>"""
FOXGLOVE_CLIENT = """
import json, sys, time
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
url, seconds = sys.argv[1], float(sys.argv[2])
count, end = 0, time.monotonic() + seconds
with connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
    ws.recv(); channels = json.loads(ws.recv())["channels"]
    subs = [{"id": i, "channelId": c["id"]} for i, c in enumerate(channels)]
    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
    print("ready", flush=True)
    while (left := end - time.monotonic()) > 0:
        try:
            count += isinstance(ws.recv(timeout=left), bytes)
        except (TimeoutError, ConnectionClosed):  # the server stopped
            break
print(count, flush=True)
"""


class Consumer:
    """A consumer process; a thread reads its output as it comes (a full pipe would stall
    it) and counts messages: the ROS 2 peer prints one line per message, the Foxglove
    client its count at the end. Both end by themselves when the publisher finishes."""

    def __init__(self, *argv: str):
        self.proc = subprocess.Popen([sys.executable, *argv], stdout=subprocess.PIPE, text=True)
        assert "ready" in self.proc.stdout.readline()
        self.lines, self.last = 0, ""
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines += line.startswith('{"topic"')
            self.last = line.strip()

    def received(self) -> int:
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.terminate()
            self.proc.wait(10)
        self.thread.join(10)
        return int(self.last) if self.last.isdigit() else self.lines


def _consumers(sensor: LiveSensor, ros2: bool, foxglove: bool, seconds: float):
    """Start the publishers, each with a consumer process attached and subscribed."""
    publishers, consumers = [], []
    if ros2:
        from beadsight.live.outputs.ros2 import Ros2Publisher

        consumers.append(Consumer(str(PEER), str(DOMAIN), "/beadsight", str(seconds + 60)))
        publishers.append(Ros2Publisher(domain_id=DOMAIN))
    if foxglove:
        from beadsight.live.outputs.foxglove import FoxgloveServer

        publishers.append(FoxgloveServer(sensor.geometry, port=0))
        url = publishers[-1].url
        consumers.append(Consumer("-c", FOXGLOVE_CLIENT, url, str(seconds + 60)))
    for publisher in publishers:
        deadline = time.monotonic() + 10
        while not all(publisher.subscribers().values()) and time.monotonic() < deadline:
            time.sleep(0.01)
        sensor.add_listener(publisher)
    return publishers, consumers


def run(name: str, args: argparse.Namespace) -> dict:
    ros2, foxglove = ROWS[name]
    rows: list[tuple[float, float]] = []  # (arrival, latency)
    timing = threading.Event()

    def on_update(update) -> None:
        if timing.is_set():
            rows.append((time.monotonic(), update.latency_s))

    settings = LiveSettings(backend=args.backend, precision=args.precision, source_fps=args.fps)
    sensor = LiveSensor(None, "sim", settings)
    sensor.on_update(on_update)
    sensor.open()
    publishers, consumers = _consumers(sensor, ros2, foxglove, args.seconds)
    with sensor:
        while sensor.stats().readings < args.warmup and not sensor.wait(0.05):
            pass
        skipped0 = sensor.stats().skipped_frames
        timing.set()
        start = time.monotonic()
        sensor.wait(args.seconds)
        timing.clear()
        elapsed = time.monotonic() - start
        skipped = sensor.stats().skipped_frames - skipped0
    for publisher in publishers:
        publisher.finish()
    received = sum(c.received() for c in consumers)
    if sensor.error is not None:
        raise sensor.error
    latency = np.array([lat for _, lat in rows]) * 1e3
    p50, p99 = np.percentile(latency, [50, 99]) if len(latency) else (np.nan, np.nan)
    return {
        "outputs": name,
        "backend": sensor.predictor.backend.describe(),
        "readings_per_s": len(rows) / elapsed,
        "skipped_frames": skipped,
        "latency_p50_ms": float(p50),
        "latency_p99_ms": float(p99),
        "published": [p.published for p in publishers],
        "skipped": [p.skipped for p in publishers],
        "publish_ms": [1e3 * p.busy_s / max(p.published, 1) for p in publishers],
        "consumer_messages": received,
        "seconds": elapsed,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--precision", default="auto")
    parser.add_argument("--fps", type=float, default=30.0, help="simulated camera rate")
    parser.add_argument("--seconds", type=float, default=12.0, help="timed seconds per row")
    parser.add_argument("--warmup", type=int, default=30, help="readings before timing")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if "CYCLONEDDS_URI" not in os.environ:
            config = Path(tmp) / "cyclonedds.xml"
            config.write_text(LOOPBACK)
            os.environ["CYCLONEDDS_URI"] = config.as_uri()
        results = [run(name, args) for name in args.rows]
    cpu = cpu_summary()
    if args.json:
        print(json.dumps({"cpu": cpu, "rows": results}, indent=2))
        return 0
    print(
        f"live outputs, shipped sim model, simulator at {args.fps:g} fps, {args.seconds:g} s per row"
    )
    print(cpu)
    print(
        f"{'outputs':<9} {'backend':<16} {'Hz':>6} {'skipped':>7} {'lat p50':>8} {'lat p99':>8} "
        f"{'published':>10} {'skipped':>8} {'consumer msgs':>13} {'publish ms':>10}"
    )
    for r in results:
        print(
            f"{r['outputs']:<9} {r['backend'][:16]:<16} {r['readings_per_s']:6.1f} "
            f"{r['skipped_frames']:7d} {r['latency_p50_ms']:8.2f} {r['latency_p99_ms']:8.2f} "
            f"{'/'.join(map(str, r['published'])) or '-':>10} "
            f"{'/'.join(map(str, r['skipped'])) or '-':>8} {r['consumer_messages']:13d} "
            f"{'/'.join(f'{x:.2f}' for x in r['publish_ms']) or '-':>10}"
        )
    base = [r for r in results if r["outputs"] == "none"]
    both = [r for r in results if r["outputs"] == "both"]
    if base and both:  # repeated rows: their medians
        p99 = {
            k: np.median([r["latency_p99_ms"] for r in rs])
            for k, rs in (("none", base), ("both", both))
        }
        delta = p99["both"] - p99["none"]
        ok = min(r["readings_per_s"] for r in both) >= args.fps * 0.98 and delta <= 5.0
        print(
            f"target (both on: {args.fps:g} Hz kept, p99 within 5 ms): "
            f"p99 {delta:+.2f} ms, {'met' if ok else 'NOT met'}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
