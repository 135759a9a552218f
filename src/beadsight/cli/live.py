"""``beadsight live`` and ``beadsight to-mcap``: argument parsing only."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    from beadsight.live.stream import DEFAULT_PORT as STREAM_PORT
    from beadsight.live.viewer.server import DEFAULT_MAX_FPS, DEFAULT_MAX_KPA
    from beadsight.live.viewer.server import DEFAULT_PORT as VIEWER_PORT

    p = subparsers.add_parser(
        "live",
        help="pressure readings from a camera, video or the simulator, with a web viewer",
        description="Run a checkpoint on frames from a camera, a video file or the simulator "
        "at the camera rate. Serves a web viewer (camera, kPa map, force trace, rate and "
        "latency, record button) and a TCP stream of readings for robot programs "
        "(docs/live.md); --output records readings to HDF5 or MCAP.",
    )
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="checkpoint file (.pt); default: the shipped sim model",
    )
    p.add_argument(
        "--source",
        default="sim",
        help="camera index (0, 1, ...), video file, or 'sim' (default)",
    )
    p.add_argument(
        "--backend",
        default="auto",
        help="auto (default), torch, compile, onnx, openvino, cuda",
    )
    p.add_argument("--precision", default="auto", help="auto (default), fp32, bf16")
    p.add_argument(
        "--preprocess",
        default="auto",
        help="frame preprocessing: auto (default: model-size frames as they are, 1280x1024 "
        "through the reference unwarp, other sizes refused); or reference, reference-linear, "
        "none, or a fisheye calibration .json",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="simulator rate (default 30) or rate asked of a camera; videos play at their own rate",
    )
    p.add_argument("--loop", action="store_true", help="restart a video file at its end")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("--host", default="127.0.0.1", help="address of the viewer and stream")
    p.add_argument(
        "--port",
        type=int,
        default=VIEWER_PORT,
        help=f"viewer port (default {VIEWER_PORT}; 0 = any free port)",
    )
    p.add_argument("--no-viewer", action="store_true", help="headless: no web viewer")
    p.add_argument(
        "--max-fps",
        type=float,
        default=DEFAULT_MAX_FPS,
        help=f"viewer updates per second (default {DEFAULT_MAX_FPS:g})",
    )
    p.add_argument(
        "--max-kpa",
        type=float,
        default=DEFAULT_MAX_KPA,
        help=f"top of the fixed colour scale, kPa (default {DEFAULT_MAX_KPA:g})",
    )
    p.add_argument(
        "--record-dir",
        type=Path,
        default=Path("."),
        help="folder for the viewer's record button (default: current folder)",
    )
    p.add_argument(
        "--stream-port",
        type=int,
        default=STREAM_PORT,
        help=f"TCP port of the readings stream (default {STREAM_PORT}; 0 = any)",
    )
    p.add_argument("--no-stream", action="store_true", help="no TCP readings stream")
    p.add_argument(
        "--output",
        type=Path,
        default=None,
        help="record every reading to this file (.h5 readings file or .mcap)",
    )
    p.add_argument("--frames", type=int, default=None, help="stop sensing after N readings")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    p.add_argument(
        "--report-every",
        type=float,
        default=5.0,
        help="seconds between rate/latency lines (default 5)",
    )
    p.set_defaults(func=run_live_command)

    p = subparsers.add_parser(
        "to-mcap",
        help="convert a readings file (beadsight live --output x.h5) to MCAP with ROS 2 types",
        description="Pressure maps as sensor_msgs/msg/Image (32FC1, kPa), total force as "
        "geometry_msgs/msg/WrenchStamped (force.z, N), centre of pressure as "
        "geometry_msgs/msg/PointStamped (m, frame 'beadsight'); stamps = capture times.",
    )
    p.add_argument("readings", type=Path, help="readings file (.h5)")
    p.add_argument("--out", required=True, type=Path, help="output .mcap file")
    p.set_defaults(func=run_to_mcap)


def run_live_command(args: argparse.Namespace) -> int:
    from beadsight.live.run import run_live
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    settings = LiveSettings(
        backend=args.backend,
        precision=args.precision,
        preprocess=args.preprocess,
        source_fps=args.fps,
        loop=args.loop,
        seed=args.seed,
        max_readings=args.frames,
    )
    sensor = LiveSensor(args.checkpoint, source=args.source, settings=settings)
    run_live(
        sensor,
        viewer=not args.no_viewer,
        host=args.host,
        port=args.port,
        viewer_options={
            "max_fps": args.max_fps,
            "max_kpa": args.max_kpa,
            "record_dir": args.record_dir,
        },
        stream_port=None if args.no_stream else args.stream_port,
        output=args.output,
        duration_s=args.duration,
        report_every_s=args.report_every,
        echo=lambda line: print(line, flush=True),
    )
    return 0


def run_to_mcap(args: argparse.Namespace) -> int:
    from beadsight.live.mcap import export_mcap

    print(f"wrote {export_mcap(args.readings, args.out)}")
    return 0
