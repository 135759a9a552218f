"""``beadsight live`` and ``beadsight to-mcap``: argument parsing only."""

from __future__ import annotations

import argparse
from pathlib import Path

from beadsight.cli.health import drift_arguments


def register(commands) -> None:
    commands.add("live", run_live_command, _live_arguments)
    commands.add("to-mcap", run_to_mcap, _to_mcap_arguments)


def _to_mcap_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("readings", type=Path, help="readings file (.h5)")
    p.add_argument("--out", required=True, type=Path, help="output .mcap file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")


def _live_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.inference.config import BACKENDS, PRECISIONS

    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="checkpoint file (.pt); default: the shipped sim model",
    )
    # LiveSensor / run_live settings: None = not given, the library's default applies
    p.add_argument(
        "--source",
        default=None,
        help="camera index (0, 1, ...), video file, dataset file (.h5: its rows replayed), or sim",
    )
    p.add_argument(
        "--backend",
        default=None,
        help=f"auto (the fastest that agrees with fp32 torch), {', '.join(BACKENDS)}",
    )
    p.add_argument("--precision", default=None, help=f"auto, {', '.join(PRECISIONS)}")
    p.add_argument(
        "--preprocess",
        default="auto",
        help="frame preprocessing: auto (default: model-size frames as they are, 1280x1024 "
        "through the reference unwarp, other sizes refused); or reference, reference-linear, "
        "none, or a fisheye lens .json",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="simulator rate (default: its camera rate), replayed dataset rate (default: the file's) "
        "or rate asked of a camera; videos play at their own rate",
    )
    p.add_argument("--loop", action="store_true", help="restart a video or dataset file at its end")
    p.add_argument("--seed", type=int, default=None, help="simulator seed")
    drift_arguments(p)
    _output_arguments(p)
    _robot_arguments(p)
    p.add_argument(
        "--output",
        type=Path,
        default=None,
        help="record every reading to this file (.h5 readings file or .mcap)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output file")
    p.add_argument("--frames", type=int, default=None, help="stop sensing after N readings")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    p.add_argument(
        "--report-every", type=float, default=None, help="seconds between rate/latency lines"
    )


def _output_arguments(p: argparse.ArgumentParser) -> None:
    """Where the readings go: the web viewer (ROS 2 and Foxglove: _robot_arguments)."""
    from beadsight.cli.options import add_option
    from beadsight.live.config import (
        DEFAULT_HOST,
        MAX_AGE_S,
        VIEWER_MAX_FPS,
        VIEWER_MAX_KPA,
        VIEWER_PORT,
    )

    add_option(p, "--host", DEFAULT_HOST, "address of the viewer and the Foxglove server")
    add_option(p, "--port", VIEWER_PORT, "viewer port (0 = any free port)")
    p.add_argument("--no-viewer", action="store_true", help="headless: no web viewer")
    add_option(p, "--max-fps", VIEWER_MAX_FPS, "viewer updates per second")
    add_option(p, "--max-kpa", VIEWER_MAX_KPA, "top of the fixed colour scale, kPa")
    p.add_argument(
        "--record-dir",
        type=Path,
        default=Path("."),
        help="folder for the viewer's record button (default: current folder)",
    )
    add_option(
        p,
        "--max-age",
        MAX_AGE_S,
        "ROS 2 and Foxglove never publish a reading older than this, s (slow clients skip "
        "readings)",
    )


def _robot_arguments(p: argparse.ArgumentParser) -> None:
    """ROS 2 topics over DDS and the Foxglove WebSocket server (docs/live.md)."""
    from beadsight.cli.options import add_option
    from beadsight.live.config import FOXGLOVE_MAX_CLIENTS, FOXGLOVE_PORT, ROS_NAMESPACE

    g = p.add_argument_group(
        "ROS 2 and Foxglove", "need the 'ros' extra: pip install 'beadsight[ros]'"
    )
    g.add_argument(
        "--ros2",
        action="store_true",
        help="publish ROS 2 topics (pressure, force, cop, contact_area, health) with Cyclone "
        "DDS, no ROS install needed; any ROS 2 node on the network receives them",
    )
    g.add_argument(
        "--ros-domain",
        type=int,
        default=None,
        metavar="N",
        help="ROS 2 domain id 0..232 (default: $ROS_DOMAIN_ID, else 0)",
    )
    add_option(
        g,
        "--ros-namespace",
        ROS_NAMESPACE,
        "namespace of the ROS 2 topics and Foxglove channels",
    )
    g.add_argument(
        "--ros-camera",
        action="store_true",
        help="also publish the model-input camera frame (<namespace>/camera, rgb8)",
    )
    g.add_argument(
        "--foxglove",
        action="store_true",
        help="serve camera, pressure map, force, CoP and health to Foxglove (app or web) "
        "over WebSocket on --host; layout: docs/foxglove-layout.json",
    )
    add_option(g, "--foxglove-port", FOXGLOVE_PORT, "Foxglove WebSocket port (0 = any free port)")
    g.add_argument(
        "--foxglove-allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="also accept browser pages from this origin (repeatable), e.g. "
        "https://app.foxglove.dev; by default only programs and local pages connect",
    )
    add_option(
        g, "--foxglove-max-clients", FOXGLOVE_MAX_CLIENTS, "Foxglove clients at once (more: 503)"
    )


def run_live_command(args: argparse.Namespace) -> int:
    """Pressure readings from a camera, video or the simulator, with a web viewer.

    Run a checkpoint on frames from a camera, a video file or the simulator at the camera
    rate. Serves a web viewer (camera, kPa map, force trace, rate and latency, record
    button); for robot programs --ros2 publishes ROS 2 topics and --foxglove serves
    Foxglove's WebSocket protocol (docs/live.md); --output records readings to HDF5 or
    MCAP.
    """
    from beadsight.cli.options import given
    from beadsight.live.config import LiveRunConfig
    from beadsight.live.run import run_live
    from beadsight.live.sensor import LiveSensor
    from beadsight.live.settings import LiveSettings

    settings = LiveSettings(
        preprocess=args.preprocess,
        source_fps=args.fps,
        loop=args.loop,
        max_readings=args.frames,
        rest_file=args.rest,
        sim_drift=args.sim_drift,
        **given(backend=args.backend, precision=args.precision, seed=args.seed),
    )
    ros_domain = args.ros_domain
    if ros_domain is None:  # ROS 2 nodes read $ROS_DOMAIN_ID; beadsight only for --ros2
        from beadsight.live.outputs.ros2 import domain_from_environment

        ros_domain = domain_from_environment() if args.ros2 else 0
    config = LiveRunConfig(
        viewer=not args.no_viewer,
        host=args.host,
        port=args.port,
        max_fps=args.max_fps,
        max_kpa=args.max_kpa,
        record_dir=args.record_dir,
        ros2=args.ros2,
        ros_domain=ros_domain,
        ros_namespace=args.ros_namespace,
        ros_camera=args.ros_camera,
        foxglove=args.foxglove,
        foxglove_port=args.foxglove_port,
        foxglove_allow_origins=tuple(args.foxglove_allow_origin),
        foxglove_max_clients=args.foxglove_max_clients,
        max_age_s=args.max_age,
        output=args.output,
        overwrite=args.overwrite,
        duration_s=args.duration,
        **given(report_every_s=args.report_every),
    )
    sensor = LiveSensor(args.checkpoint, settings=settings, **given(source=args.source))
    run_live(sensor, config, echo=lambda line: print(line, flush=True))
    return 0


def run_to_mcap(args: argparse.Namespace) -> int:
    """Convert a readings file (beadsight live --output x.h5) to MCAP with ROS 2 types.

    Pressure maps as sensor_msgs/msg/Image (32FC1, kPa), total force as
    geometry_msgs/msg/WrenchStamped (force.z, N), centre of pressure as
    geometry_msgs/msg/PointStamped (m, frame 'beadsight'); stamps = capture times.
    """
    from beadsight.live.recording.mcap import export_mcap

    print(f"wrote {export_mcap(args.readings, args.out, overwrite=args.overwrite)}")
    return 0
