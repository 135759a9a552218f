"""``beadsight collect`` and ``beadsight process``: the calibration rig's commands."""

from __future__ import annotations

import argparse
from pathlib import Path

EXIT_CODES = {"complete": 0, "interrupted": 130}  # any other status: 1


def register(sub: argparse._SubParsersAction) -> None:
    _register_collect(sub)
    _register_process(sub)


# --- collect ---------------------------------------------------------------------------------
def _register_collect(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "collect",
        help="press the finger onto the sensor following a plan and record everything",
        description="Run a press plan on the rig (real devices, or --virtual for the simulated "
        "rig) and record video, scale readings and printer commands into a raw recording "
        "folder. Ctrl-C stops cleanly (finger lifted, files closed); --resume continues.",
    )
    p.add_argument("--out", type=Path, required=True, help="raw recording folder to create")
    src = p.add_argument_group("devices")
    src.add_argument("--virtual", action="store_true", help="use the simulated rig")
    src.add_argument("--printer", metavar="PORT", help="printer serial port (/dev/ttyUSB0)")
    src.add_argument("--scale", metavar="PORT", help="scale serial port (/dev/ttyACM0)")
    src.add_argument("--camera", metavar="INDEX_OR_PATH", help="camera index or video file")
    src.add_argument("--printer-baud", type=int, default=115200)
    src.add_argument("--scale-baud", type=int, default=57600)
    src.add_argument("--scale-protocol", choices=("auto", "beadsight", "reference"), default="auto")
    src.add_argument(
        "--camera-size", type=int, nargs=2, default=(1280, 1024), metavar=("WIDTH", "HEIGHT")
    )
    src.add_argument("--camera-fps", type=float, default=30.0)
    plan = p.add_argument_group("press plan (defaults: the reference pattern)")
    plan.add_argument("--plan", type=Path, help="TOML file with PressPlan fields")
    plan.add_argument("--presses", type=int, help="data presses (default 500)")
    plan.add_argument("--pattern", choices=("random", "grid"))
    plan.add_argument("--seed", type=int, help="plan seed (locations and depths)")
    plan.add_argument("--calibration-presses", type=int, help="centre presses first (default 3)")
    safety = p.add_argument_group("safety and session")
    safety.add_argument(
        "--force-limit",
        type=float,
        default=40.0,
        metavar="N",
        help="abort a press above this force, newtons (default 40)",
    )
    safety.add_argument(
        "--on-force-limit",
        choices=("stop", "skip"),
        default="stop",
        help="after an aborted press: stop the session or go on",
    )
    safety.add_argument(
        "--scale-timeout",
        type=float,
        default=2.0,
        metavar="S",
        help="stop (finger lifted) when the scale is silent this long (default 2)",
    )
    safety.add_argument(
        "--resume", action="store_true", help="continue the session in --out with its saved plan"
    )
    safety.add_argument("--chunk-frames", type=int, help="frames per video chunk (default: fps)")
    safety.add_argument("--no-progress", action="store_true")
    virt = p.add_argument_group("virtual rig (--virtual)")
    virt.add_argument(
        "--time-scale", type=float, default=1.0, help="simulated seconds per real second"
    )
    virt.add_argument(
        "--virtual-camera",
        choices=("raw", "sensor"),
        default="raw",
        help="raw 1280x1024 fisheye frames, or sensor-space frames (fast)",
    )
    virt.add_argument(
        "--image-size",
        type=int,
        default=256,
        help="sensor-space frame size for --virtual-camera sensor",
    )
    virt.add_argument("--sim-seed", type=int, default=0, help="seed of the simulated pouch")
    p.set_defaults(func=_collect)


def _collect(args: argparse.Namespace) -> int:
    from beadsight.rig.collect import (
        DeviceSpec,
        PressPlan,
        VirtualRigSpec,
        collect_with_hardware,
        collect_with_virtual_rig,
        simulator_config,
    )
    from beadsight.errors import BeadSightError

    overrides = {
        "presses": args.presses,
        "pattern": args.pattern,
        "seed": args.seed,
        "calibration_presses": args.calibration_presses,
    }
    options = {
        "resume": args.resume,
        "force_limit_n": args.force_limit,
        "on_force_limit": args.on_force_limit,
        "chunk_frames": args.chunk_frames,
        "progress": not args.no_progress,
        "scale_timeout_s": args.scale_timeout,
    }
    if args.virtual:
        if args.printer or args.scale or args.camera:
            raise BeadSightError(
                "--virtual replaces --printer, --scale and --camera; give one or the other"
            )
        rig = VirtualRigSpec(
            time_scale=args.time_scale,
            camera_mode=args.virtual_camera,
            image_size_px=args.image_size,
            seed=args.sim_seed,
        )
        plan = (
            PressPlan.from_toml(args.plan, **overrides)
            if args.plan
            else PressPlan.for_simulator(simulator_config(rig), **overrides)
        )
        result = collect_with_virtual_rig(rig, plan, args.out, **options)
    else:
        missing = [f"--{n}" for n in ("printer", "scale", "camera") if not getattr(args, n)]
        if missing:
            raise BeadSightError(f"missing {', '.join(missing)} (or use --virtual)")
        spec = DeviceSpec(
            args.printer,
            args.scale,
            args.camera,
            args.printer_baud,
            args.scale_baud,
            args.scale_protocol,
            args.camera_size[0],
            args.camera_size[1],
            args.camera_fps,
        )
        plan = (
            PressPlan.from_toml(args.plan, **overrides)
            if args.plan
            else PressPlan(**{k: v for k, v in overrides.items() if v is not None})
        )
        result = collect_with_hardware(spec, plan, args.out, **options)
    print(f"{result.path}: {result.status}: {result.message}")
    print(
        f"{result.presses_done}/{result.presses_total} presses, {result.frames} frames, "
        f"{result.readings} scale readings"
        + (f"; aborted presses {result.aborted}" if result.aborted else "")
    )
    return EXIT_CODES.get(result.status, 1)


# --- process ---------------------------------------------------------------------------------
def _register_process(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "process",
        help="turn a raw recording (this project's or the reference's) into a dataset",
        description="Align frames with the force and printer logs, preprocess the images and "
        "write an HDF5 dataset plus a QA summary (<out>.qa.json, <out>.qa.png).",
    )
    p.add_argument("raw", type=Path, help="raw recording folder")
    p.add_argument("--out", type=Path, required=True, help="dataset file to write (.h5)")
    p.add_argument(
        "--preprocess",
        default="reference",
        help="'reference' (fisheye unwarp as published), 'none', or a fisheye "
        "calibration .json (default: reference)",
    )
    p.add_argument("--image-size", type=int, default=256, help="output image side, px")
    p.add_argument(
        "--interpolation",
        choices=("linear", "reference"),
        default="linear",
        help="unwarp sampling: bilinear, or the reference's truncating nearest "
        "neighbour (bit-compatible, slower)",
    )
    p.add_argument(
        "--resize",
        choices=("supersample", "area", "linear"),
        default="supersample",
        help="downscaling: supersample (antialiased, fast), area (cv2.INTER_AREA), "
        "linear (no antialiasing)",
    )
    p.add_argument(
        "--force-interpolation",
        choices=("pchip", "cubic", "linear"),
        default="pchip",
        help="force at frame times (cubic = the reference's spline)",
    )
    p.add_argument(
        "--max-force-gap",
        type=float,
        default=0.5,
        metavar="S",
        help="frames in a longer gap between scale readings are invalid",
    )
    p.add_argument(
        "--camera-delay",
        type=float,
        default=0.0,
        metavar="S",
        help="camera latency subtracted from frame timestamps",
    )
    p.add_argument(
        "--decode-scale",
        type=int,
        choices=(0, 1, 2, 4, 8),
        default=0,
        help="JPEG decode reduction; 0 = automatic",
    )
    p.add_argument("--workers", type=int, default=0, help="threads (0 = one per core)")
    p.add_argument("--compression", choices=("gzip", "lzf"), default=None)
    p.add_argument(
        "--force-counter",
        choices=("auto", "on", "off"),
        default="auto",
        help="decode the reference scale sketch's +10000*i counter in the force log: auto "
        "(when the values step through its 0..9 cycle), on, off (default: auto)",
    )
    p.add_argument(
        "--scale-capacity",
        type=float,
        default=50.0,
        metavar="N",
        help="scale capacity in newtons: readings beyond it are reported and the frames "
        "labelled from them are invalid (default: 50)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_process)


def _process(args: argparse.Namespace) -> int:
    from beadsight.data.process import ProcessConfig, process_recording, qa_paths

    config = ProcessConfig(
        image_size=args.image_size,
        preprocess=args.preprocess,
        interpolation=args.interpolation,
        resize=args.resize,
        force_interpolation=args.force_interpolation,
        max_force_gap_s=args.max_force_gap,
        camera_delay_s=args.camera_delay,
        decode_scale=args.decode_scale,
        workers=args.workers,
        compression=args.compression,
        force_counter=args.force_counter,
        scale_capacity_n=args.scale_capacity,
    )
    qa = process_recording(
        args.raw, args.out, config, progress=not args.no_progress, overwrite=args.overwrite
    )
    json_path, png_path = qa_paths(args.out)
    invalid = ", ".join(f"{k} {v}" for k, v in qa["invalid_frames"].items()) or "none"
    dropped = qa["dropped_frames"]["total"]
    print(
        f"wrote {args.out}: {qa['frames_written']} frames ({qa['frames_valid']} valid), "
        f"{qa['presses']} presses, {dropped} dropped frames; invalid: {invalid}"
    )
    if qa["force_n"]["max"] is not None:
        print(
            f"force {qa['force_n']['min']:.2f} .. {qa['force_n']['max']:.2f} N; "
            f"{qa['frames_per_s']:.0f} frames/s"
        )
    if qa["force_counter"]["decoded"]:
        print(qa["force_counter"]["message"])
    for w in qa["warnings"]:
        print(f"warning: {w}")
    print(f"QA: {json_path}, {png_path}")
    return 0
