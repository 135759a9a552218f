"""Time from the start of each simulated drift to the health states ``drifting`` and
``recalibrate`` (the simulated pouch at rest, 64 px frames like the shipped model's).

    .venv/bin/python benchmarks/health_drift.py [--seconds 60]

Drift kinds at their defaults (beadsight.sim.drift): settle (1.2 mm at the edge, time
constant 20 s), light (-40 % brightness, +-20 % red/blue over 30 s), bump (1 mm at
5 s) and a 2 mm bump.
"""

from __future__ import annotations

import argparse
import time

from beadsight.health.checkup import drift_timeline
from beadsight.inference.machine import cpu_summary

KINDS_STATES = ("ok", "drifting", "recalibrate")
KINDS = ("none", "settle", "light", "bump", "bump,bump_mm=2")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per kind")
    args = p.parse_args()
    print(cpu_summary())
    for kind in KINDS:
        start = time.perf_counter()
        first = drift_timeline(None if kind == "none" else kind, args.seconds)
        wall = time.perf_counter() - start

        at = {s: f"{first[s]:5.1f} s" if s in first else "  never" for s in KINDS_STATES}
        print(
            f"{kind:16s} ok at {at['ok']}, drifting at {at['drifting']}, recalibrate at "
            f"{at['recalibrate']} ({wall:.1f} s wall)"
        )


if __name__ == "__main__":
    main()
