"""Read live pressure readings from `beadsight live` over TCP, without beadsight installed.

    beadsight live --source sim              # serves the stream on 127.0.0.1:8765
    python examples/stream_client.py --count 100
    python examples/stream_client.py --interval 0.1   # a 10 Hz control loop

Needs only the standard library and numpy. Prints one JSON line per reading: capture
timestamp, its age when read (s), total force (N) from the header and recomputed from the
map, centre of pressure (mm, null without contact), peak pressure (kPa), and `seq` /
`skipped` (readings this client missed because it read slower than the sensor). Status
changes ("no_signal", "ended") go to stderr. The message format is in docs/live.md.

The server never sends a reading older than its limit (0.5 s by default), but what waits
in this program's own socket buffer ages there: a client that reads slower than the
sensor keeps that buffer small (--rcvbuf, set before connecting) so that each reading
it reads is fresh.
"""

import argparse
import itertools
import json
import socket
import sys
import time

import numpy as np

RCVBUF_BYTES = 16384  # small: readings do not queue up in this client's socket buffer


def messages(host="127.0.0.1", port=8765, rcvbuf=RCVBUF_BYTES):
    """Yield (header dict, payload bytes) for every message of the stream."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # before connect()
    with sock:
        sock.connect((host, port))
        with sock.makefile("rb") as stream:
            while line := stream.readline():  # one JSON header line per message ...
                header = json.loads(line)
                yield header, stream.read(header["payload_bytes"])  # ... then its payload


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8765)
    parser.add_argument("--count", type=int, default=0, help="stop after N readings (0: never)")
    parser.add_argument(
        "--interval", type=float, default=0.0, help="seconds to wait after each reading"
    )
    parser.add_argument(
        "--rcvbuf",
        type=int,
        default=RCVBUF_BYTES,
        help=f"socket receive buffer, bytes (default {RCVBUF_BYTES}; 0: the system's)",
    )
    args = parser.parse_args()
    mm_per_px, count = None, 0
    try:
        stream = messages(args.host, args.port, args.rcvbuf)
        first = next(stream)
    except ConnectionRefusedError:
        sys.exit(f"no stream on {args.host}:{args.port}: is `beadsight live` running?")
    for header, payload in itertools.chain([first], stream):
        if header["type"] == "hello":
            mm_per_px = header["mm_per_px"]
        elif header["type"] == "status":
            print(
                f"status: {header['state']}: {header['message']} (seq {header.get('seq')}, "
                f"skipped {header.get('skipped')})",
                file=sys.stderr,
                flush=True,
            )
        elif header["type"] == "reading":
            age_s = time.time() - header["timestamp_s"]
            kpa = np.frombuffer(payload, "<f4").reshape(header["height"], header["width"])
            map_force_n = float(kpa.sum(dtype=np.float64)) * mm_per_px**2 * 1e-3  # kPa*mm^2 -> N
            line = {
                "seq": header["seq"],
                "skipped": header["skipped"],
                "timestamp_s": header["timestamp_s"],
                "age_s": round(age_s, 4),
                "frame_index": header["frame_index"],
                "force_n": header["force_n"],
                "map_force_n": map_force_n,
                "cop_mm": header["cop_mm"],
                "peak_kpa": float(kpa.max()),
            }
            print(json.dumps(line), flush=True)
            count += 1
            if count == args.count:
                return 0
            if args.interval > 0:
                time.sleep(args.interval)
    return 0


if __name__ == "__main__":
    sys.exit(main())
