"""``beadsight collect`` and ``beadsight process``: the calibration rig's commands.

Options and their defaults come from the dataclasses the commands build:
:class:`~beadsight.rig.config.DeviceSpec`, :class:`~beadsight.rig.config.VirtualRigSpec`,
:class:`~beadsight.rig.plan.PressPlan` and :class:`~beadsight.data.process.config.ProcessConfig`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from beadsight.rig.config import CAMERA_MODES, SCALE_PROTOCOLS  # light: no numpy

EXIT_CODES = {"complete": 0, "interrupted": 130}  # any other status: 1
NAMED_PLANS = ("calibration",)  # --plan NAME instead of a TOML file: that pattern

DEVICE_FLAGS = (
    ("printer_baud", "printer serial baud rate"),
    ("scale_baud", "scale serial baud rate"),
    ("scale_protocol", "scale line format", {"choices": SCALE_PROTOCOLS}),
    ("camera_fps", "camera frame rate asked for"),
)
PLAN_FLAGS = (  # None unless given: a --plan file's values, else PressPlan's, apply
    ("presses", "data presses"),
    ("pattern", "press locations: random, grid or calibration"),
    ("seed", "plan seed (locations and depths)"),
    ("calibration_presses", "centre presses first"),
)
VIRTUAL_FLAGS = (
    ("time_scale", "simulated seconds per real second"),
    (
        "camera_mode",
        "raw 1280x1024 fisheye frames, or sensor-space frames (fast)",
        {"flag": "--virtual-camera", "choices": CAMERA_MODES},
    ),
    (
        "image_size_px",
        "sensor-space frame size for --virtual-camera sensor",
        {"flag": "--image-size"},
    ),
    ("seed", "seed of the simulated pouch", {"flag": "--sim-seed", "dest": "sim_seed"}),
)
PROCESS_FLAGS = (
    (
        "preprocess",
        "'reference' (fisheye unwarp as published), 'none', or a fisheye lens .json",
    ),
    ("image_size", "output image side, px"),
    (
        "interpolation",
        "unwarp sampling: bilinear, or the reference's truncating nearest neighbour "
        "(bit-compatible, slower)",
        {"choices": ("linear", "reference")},
    ),
    (
        "resize",
        "downscaling: supersample (antialiased, fast), area (cv2.INTER_AREA), linear "
        "(no antialiasing)",
        {"choices": ("supersample", "area", "linear")},
    ),
    (
        "force_interpolation",
        "force at frame times (cubic = the reference's spline)",
        {"choices": ("pchip", "cubic", "linear")},
    ),
    (
        "max_force_gap_s",
        "frames in a longer gap between scale readings are invalid",
        {"flag": "--max-force-gap", "metavar": "S"},
    ),
    (
        "camera_delay_s",
        "camera latency subtracted from frame timestamps",
        {"flag": "--camera-delay", "metavar": "S"},
    ),
    ("decode_scale", "JPEG decode reduction; 0 = automatic", {"choices": (0, 1, 2, 4, 8)}),
    ("workers", "threads (0 = one per core)"),
    ("compression", "HDF5 compression of the frames", {"choices": ("gzip", "lzf"), "type": str}),
    (
        "force_counter",
        "decode the reference scale sketch's +10000*i counter in the force log: auto (when "
        "the values step through its 0..9 cycle), on, off",
        {"choices": ("auto", "on", "off")},
    ),
    (
        "scale_capacity_n",
        "scale capacity in newtons: readings beyond it are reported and the frames labelled "
        "from them are invalid",
        {"flag": "--scale-capacity", "metavar": "N"},
    ),
)


def register(commands) -> None:
    commands.add("collect", _collect, _collect_arguments)
    commands.add("process", _process, _process_arguments)


# --- collect ---------------------------------------------------------------------------------
def _collect_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_fields, add_option, field_default
    from beadsight.rig.config import (
        FORCE_LIMIT_N,
        ON_FORCE_LIMIT,
        SCALE_TIMEOUT_S,
        DeviceSpec,
        VirtualRigSpec,
    )
    from beadsight.rig.plan import PressPlan

    p.add_argument("--out", type=Path, required=True, help="raw recording folder to create")
    src = p.add_argument_group("devices")
    src.add_argument("--virtual", action="store_true", help="use the simulated rig")
    src.add_argument("--printer", metavar="PORT", help="printer serial port (/dev/ttyUSB0)")
    src.add_argument("--scale", metavar="PORT", help="scale serial port (/dev/ttyACM0)")
    src.add_argument("--camera", metavar="INDEX_OR_PATH", help="camera index or video file")
    add_fields(src, DeviceSpec, DEVICE_FLAGS)
    size = (field_default(DeviceSpec, "camera_width"), field_default(DeviceSpec, "camera_height"))
    add_option(
        src, "--camera-size", size, "camera frame size asked for", nargs=2, metavar=("W", "H")
    )
    plan = p.add_argument_group("press plan (defaults: the reference pattern)")
    plan.add_argument(
        "--plan",
        metavar="FILE.toml|calibration",
        help="a TOML file with PressPlan fields, or 'calibration': positions and depths that "
        "cover the pad and the force range evenly for few presses (docs/calibration.md)",
    )
    add_fields(plan, PressPlan, PLAN_FLAGS, override=True)
    safety = p.add_argument_group("safety and session")
    add_option(
        safety, "--force-limit", FORCE_LIMIT_N, "abort a press above this force, N", metavar="N"
    )
    add_option(
        safety,
        "--on-force-limit",
        ON_FORCE_LIMIT[0],
        "after an aborted press: stop the session or go on",
        choices=ON_FORCE_LIMIT,
    )
    add_option(
        safety,
        "--scale-timeout",
        SCALE_TIMEOUT_S,
        "stop (finger lifted) when the scale is silent this long",
        metavar="S",
    )
    safety.add_argument(
        "--resume", action="store_true", help="continue the session in --out with its saved plan"
    )
    safety.add_argument("--chunk-frames", type=int, help="frames per video chunk (default: fps)")
    safety.add_argument("--no-progress", action="store_true")
    add_fields(p.add_argument_group("virtual rig (--virtual)"), VirtualRigSpec, VIRTUAL_FLAGS)


def _collect(args: argparse.Namespace) -> int:
    """Press the finger onto the sensor following a plan and record everything.

    Run a press plan on the rig (real devices, or --virtual for the simulated rig) and
    record video, scale readings and printer commands into a raw recording folder.
    Ctrl-C stops cleanly (finger lifted, files closed); --resume continues.
    """
    from beadsight.errors import BeadSightError
    from beadsight.rig.collect import (
        collect_with_hardware,
        collect_with_virtual_rig,
        simulator_config,
    )
    from beadsight.rig.config import DeviceSpec, VirtualRigSpec
    from beadsight.rig.plan import PressPlan

    overrides = {name: getattr(args, name) for name, *_ in PLAN_FLAGS}
    plan_file = None if args.plan in NAMED_PLANS else args.plan
    if args.plan in NAMED_PLANS and overrides["pattern"] is None:
        overrides["pattern"] = args.plan
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
            camera_mode=args.camera_mode,
            image_size_px=args.image_size_px,
            seed=args.sim_seed,
        )
        plan = (
            PressPlan.from_toml(plan_file, **overrides)
            if plan_file
            else PressPlan.for_simulator(simulator_config(rig), **overrides)
        )
        _announce(plan)
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
            PressPlan.from_toml(plan_file, **overrides)
            if plan_file
            else PressPlan(**{k: v for k, v in overrides.items() if v is not None})
        )
        _announce(plan)
        result = collect_with_hardware(spec, plan, args.out, **options)
    print(f"{result.path}: {result.status}: {result.message}")
    print(
        f"{result.presses_done}/{result.presses_total} presses, {result.frames} frames, "
        f"{result.readings} scale readings"
        + (f"; aborted presses {result.aborted}" if result.aborted else "")
    )
    return EXIT_CODES.get(result.status, 1)


def _announce(plan) -> None:
    print(
        f"plan: {plan.total} presses ({plan.pattern}, {plan.calibration_presses} at the centre "
        f"first), about {plan.duration_s() / 60:.1f} min of printer moves"
    )


# --- process ---------------------------------------------------------------------------------
def _process_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_fields
    from beadsight.data.process.config import ProcessConfig

    p.add_argument("raw", type=Path, help="raw recording folder")
    p.add_argument("--out", type=Path, required=True, help="dataset file to write (.h5)")
    add_fields(p, ProcessConfig, PROCESS_FLAGS)
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _process(args: argparse.Namespace) -> int:
    """Turn a raw recording (this project's or the reference's) into a dataset.

    Align frames with the force and printer logs, preprocess the images and write an
    HDF5 dataset plus a QA summary (<out>.qa.json, <out>.qa.png).
    """
    from beadsight.cli.options import field_values
    from beadsight.data.process.config import ProcessConfig
    from beadsight.data.process.run import process_recording, qa_paths

    config = ProcessConfig(**field_values(args, ProcessConfig))
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
