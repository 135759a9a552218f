"""Read live pressure readings from `beadsight live` over TCP, without beadsight installed.

    beadsight live --source sim              # serves the stream on 127.0.0.1:8765
    python examples/stream_client.py --count 100

Needs only the standard library and numpy. Prints one JSON line per reading: capture
timestamp, total force (N) from the header and recomputed from the map, centre of
pressure (mm, null without contact), peak pressure (kPa). Status changes ("no_signal",
"ended") go to stderr. The message format is documented in docs/live.md.
"""

import argparse
import itertools
import json
import socket
import sys

import numpy as np


def messages(host="127.0.0.1", port=8765):
    """Yield (header dict, payload bytes) for every message of the stream."""
    with socket.create_connection((host, port)) as sock, sock.makefile("rb") as stream:
        while line := stream.readline():  # one JSON header line per message ...
            header = json.loads(line)
            yield header, stream.read(header["payload_bytes"])  # ... then its payload


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8765)
    parser.add_argument("--count", type=int, default=0, help="stop after N readings (0: never)")
    args = parser.parse_args()
    mm_per_px, count = None, 0
    try:
        stream = messages(args.host, args.port)
        first = next(stream)
    except ConnectionRefusedError:
        sys.exit(f"no stream on {args.host}:{args.port}: is `beadsight live` running?")
    for header, payload in itertools.chain([first], stream):
        if header["type"] == "hello":
            mm_per_px = header["mm_per_px"]
        elif header["type"] == "status":
            print(f"status: {header['state']}: {header['message']}", file=sys.stderr, flush=True)
        elif header["type"] == "reading":
            kpa = np.frombuffer(payload, "<f4").reshape(header["height"], header["width"])
            map_force_n = float(kpa.sum(dtype=np.float64)) * mm_per_px**2 * 1e-3  # kPa*mm^2 -> N
            line = {
                "timestamp_s": header["timestamp_s"],
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
