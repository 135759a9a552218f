"""A press held still for 60 s of simulated time: published force against the true force.

    .venv/bin/python benchmarks/steady_press.py [--hold-s 60] [--checkpoint C] [--drift SPEC]

Runs LiveSensor on the simulator's steady press (beadsight.sim.scripted) and prints the true force, the
published force at the start and end of the hold, the largest deviation in % (the issue's
target: within 5 %) and the health state at the end.
"""

from __future__ import annotations

import argparse
import time

from beadsight.inference.machine import cpu_summary
from beadsight.live.steady import run_steady_press


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hold-s", type=float, default=60.0, help="how long the press is held, s")
    p.add_argument("--checkpoint", default=None, help="checkpoint (default: the shipped sim model)")
    p.add_argument("--drift", default=None, help="the simulator's drift, e.g. light")
    args = p.parse_args()
    print(cpu_summary())
    start = time.perf_counter()
    result = run_steady_press(args.checkpoint, args.hold_s, drift=args.drift)
    wall = time.perf_counter() - start
    print(f"{result.summary()} ({wall:.1f} s wall)")


if __name__ == "__main__":
    main()
