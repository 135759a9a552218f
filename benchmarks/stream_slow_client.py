"""Staleness of the TCP stream for a slow client: how old are the readings it reads?

Target: a client that reads 10 messages/s while the sensor runs at 30 Hz reads readings
at most ~0.5 s old (the stream's limit) plus what waits in its own receive buffer, and
`seq` / `skipped` account for every reading it missed.

    .venv/bin/python benchmarks/stream_slow_client.py
    .venv/bin/python benchmarks/stream_slow_client.py --count 80 --rcvbuf 16384 0

For each receive-buffer size (0: the system's default) the script runs a LiveSensor on the
simulator (30 fps, a 64 px width-8 model with random weights) with the stream server, and
runs examples/stream_client.py as a separate process that reads one reading every
--interval seconds. It prints the age of the readings when read (p50 / max), how many
readings the client missed (sum of `skipped`) against the gaps in `seq`, and the CPU model.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from viewer_idle_clients import tiny_model

from beadsight.inference.machine import cpu_summary
from beadsight.live.sensor import LiveSensor
from beadsight.live.settings import LiveSettings
from beadsight.live.stream import StreamServer

CLIENT = Path(__file__).resolve().parents[1] / "examples" / "stream_client.py"


def run(model, rcvbuf: int, args: argparse.Namespace) -> None:
    with (
        StreamServer(model.geometry, port=0) as server,
        LiveSensor(model, "sim", LiveSettings("torch", "fp32", source_fps=args.fps)) as sensor,
    ):
        sensor.add_listener(server)
        command = [
            sys.executable,
            str(CLIENT),
            "--port",
            str(server.port),
            "--count",
            str(args.count),
            "--interval",
            str(args.interval),
            "--rcvbuf",
            str(rcvbuf),
        ]
        done = subprocess.run(command, capture_output=True, text=True, timeout=600)
        rate = sensor.stats().rate_hz
    if done.returncode != 0:
        raise SystemExit(done.stderr)
    rows = [json.loads(line) for line in done.stdout.splitlines()]
    ages = np.array([r["age_s"] for r in rows])
    seq = [r["seq"] for r in rows]
    skipped = sum(r["skipped"] for r in rows[1:])
    gaps = sum(b - a - 1 for a, b in zip(seq, seq[1:], strict=False))
    label = "system default" if rcvbuf == 0 else f"{rcvbuf} B"
    print(
        f"receive buffer {label:>14}: {len(rows)} readings read, age p50 "
        f"{np.median(ages):.3f} s, max {ages.max():.3f} s (last {ages[-1]:.3f} s); skipped "
        f"{skipped}, seq gaps {gaps}; sensing {rate:.1f} readings/s",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rcvbuf", type=int, nargs="+", default=[16384, 0])
    parser.add_argument("--count", type=int, default=60, help="readings the client reads")
    parser.add_argument("--interval", type=float, default=0.1, help="client's wait per reading")
    parser.add_argument("--fps", type=float, default=30.0, help="simulator rate")
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)
    print(f"client reads one reading every {args.interval:g} s")
    model = tiny_model()
    for rcvbuf in args.rcvbuf:
        run(model, rcvbuf, args)


if __name__ == "__main__":
    main()
