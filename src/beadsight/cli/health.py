"""``beadsight health``: argument parsing only."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(commands) -> None:
    commands.add("health", run_health_command, _health_arguments)


def drift_arguments(p: argparse.ArgumentParser) -> None:
    """Health options shared by ``live`` and ``health``."""
    p.add_argument(
        "--rest",
        type=Path,
        default=None,
        metavar="FILE",
        help="a stored rest reference (.npz from beadsight health --save-rest): the model "
        "reads against it until the pouch is unloaded and still; default: the rest is taken "
        "from still frames at start-up (keep the pouch unloaded then)",
    )
    p.add_argument(
        "--sim-drift",
        default=None,
        metavar="SPEC",
        help="drift of the simulator source: settle, light, bump and field=value pairs, "
        "comma separated (e.g. bump,bump_at_s=9); see beadsight.sim.drift",
    )


def _health_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="checkpoint (.pt); default: the shipped sim model",
    )
    p.add_argument("--source", default="sim", help="camera index, video file, or sim")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to watch, s")
    p.add_argument("--backend", default=None, help="auto, torch, onnx, openvino, ...")
    p.add_argument("--seed", type=int, default=None, help="simulator seed")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument(
        "--save-rest",
        type=Path,
        default=None,
        metavar="FILE",
        help="save the newest rest reference to FILE (.npz) for later runs",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --save-rest")
    drift_arguments(p)


def run_health_command(args: argparse.Namespace) -> int:
    """Watch the sensor at rest and print its health: state, figures, what to do.

    Keep the pouch unloaded. Prints ok, drifting or recalibrate (unknown: no rest
    reference was taken) with the figures behind it (bead creep, camera shift,
    brightness, colour between rest states) and what to do. --save-rest stores the newest
    rest reference for beadsight live --rest and beadsight calibrate --rest.
    """
    from beadsight.cli.options import given
    from beadsight.health.checkup import run_checkup
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    settings = LiveSettings(
        rest_file=args.rest,
        sim_drift=args.sim_drift,
        **given(backend=args.backend, seed=args.seed),
    )
    sensor = LiveSensor(args.checkpoint, source=args.source, settings=settings)
    report = run_checkup(sensor, args.seconds, save_rest=args.save_rest, overwrite=args.overwrite)
    if args.json:
        print(
            json.dumps(
                {
                    "state": report.state,
                    "message": report.message,
                    "figures": report.figures,
                    "reference": report.reference,
                }
            )
        )
    else:
        print(f"health: {report.state}")
        print(report.message)
        for name, value in report.figures.items():
            print(f"  {name:22s} {value:.3f}")
    if args.save_rest is not None:
        print(f"rest reference saved to {args.save_rest}")
    return 0
