"""``beadsight export`` and ``beadsight bench live``: argument parsing only."""

from __future__ import annotations

import argparse
import json


def register(commands) -> None:
    commands.add("export", _export, _export_arguments)
    commands.add("bench", help="performance measurements", arguments=_bench_arguments)


def _export_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_option
    from beadsight.inference.config import EXPORT_FORMATS, EXPORT_PRECISIONS

    p.add_argument(
        "--checkpoint",
        default=None,
        help="beadsight or reference checkpoint; default: the shipped sim model (as live and "
        "health)",
    )
    p.add_argument(
        "--format",
        required=True,
        choices=EXPORT_FORMATS,
        help="onnx: an .onnx file for onnxruntime; openvino: an OpenVINO IR (.xml + .bin)",
    )
    p.add_argument("--out", required=True, help=".onnx file, or OpenVINO .xml")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    add_option(p, "--precision", EXPORT_PRECISIONS[0], "model precision", choices=EXPORT_PRECISIONS)
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def _bench_arguments(bench: argparse.ArgumentParser) -> None:
    sub = bench.add_subparsers(dest="bench_command", metavar="WHAT", required=True)
    live = sub.add_parser(
        "live",
        help="live predictor rate, latency and error vs fp32 torch",
        description="Feed simulated frames through PressurePredictor.update: max throughput "
        "and sustained at --rate Hz. Without --checkpoint: a randomly initialised "
        "reference-size model (width 16, 256 px, T=15).",
    )
    live.add_argument("--checkpoint", default=None)
    _backend_args(live)
    # None: not given, bench_live's defaults apply
    live.add_argument("--frames", type=int, default=None, help="frames per run")
    live.add_argument(
        "--rate", type=float, default=None, help="camera rate of the sustained run, Hz (0: skip it)"
    )
    live.add_argument("--seed", type=int, default=None, help="seed of the simulated frames")
    live.add_argument(
        "--source",
        default=None,
        help="instead: run the live loop on this source (camera index, video file, sim) "
        "and report its rate, camera-to-reading latency and camera truth (delivered fps, "
        "dropped and duplicated frames)",
    )
    live.add_argument(
        "--duration", type=float, default=10.0, help="with --source: seconds to run (default 10)"
    )
    live.add_argument("--fps", type=float, default=None, help="with --source: the rate to ask")
    live.add_argument(
        "--tiers",
        action="store_true",
        help="instead: eager torch fp32, the best fp32 runtime and int8, one after another, "
        "for the reference size (random weights, or --reference) and the shipped model (or "
        "--checkpoint): readings/s, p50/p99, speedup, whether a 30 Hz camera is held (every "
        "frame read, p99 camera-to-reading age within a frame period) and the paper's "
        "metrics vs fp32 torch, with the CPU",
    )
    live.add_argument(
        "--reference",
        default=None,
        metavar="CHECKPOINT",
        help="with --tiers: a trained reference-size checkpoint in place of the random one "
        "(random weights cannot vouch for int8 on the paper's metrics)",
    )
    live.add_argument("--json", action="store_true", help="print one JSON object")
    live.set_defaults(func=_bench_live)


def _backend_args(p: argparse.ArgumentParser) -> None:
    from beadsight.inference.config import BACKENDS, PRECISIONS

    p.add_argument(
        "--backend",
        default="auto",
        choices=("auto", *BACKENDS),
        help="inference backend (auto: fastest that agrees with fp32 torch)",
    )
    p.add_argument("--precision", default="auto", choices=("auto", *PRECISIONS))
    p.add_argument("--device", default=None, help="torch device for torch/cuda (e.g. cuda:0)")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads (default: $OMP_NUM_THREADS, else every usable core)",
    )
    p.add_argument(
        "--cache-dir",
        default="default",
        help="cache for exports, quantized models and auto decisions "
        "(default ~/.cache/beadsight; 'none' disables)",
    )


def _backend_options(args: argparse.Namespace) -> dict:
    cache = None if args.cache_dir.lower() == "none" else args.cache_dir
    return {"cache_dir": cache, "threads": args.threads}


def _export(args: argparse.Namespace) -> int:
    """Export a checkpoint to ONNX or OpenVINO (uint8 frames in, kPa out).

    Export a checkpoint with its normalisation and metadata; the file is checked against
    torch and removed if it disagrees.
    """
    from beadsight.assets import shipped_model_path
    from beadsight.inference.export import export_model

    report = export_model(
        args.checkpoint or shipped_model_path(),
        args.format,
        args.out,
        args.precision,
        overwrite=args.overwrite,
    )
    if args.json:
        print(json.dumps(report.to_dict()))
    else:
        print(
            f"wrote {report.path} ({report.format}, {report.precision}); parity vs torch: "
            f"max abs error {report.max_abs_err_kpa:.3g} kPa "
            f"(tolerance {report.tolerance_kpa:.3g} kPa, peak {report.peak_kpa:.3g} kPa)"
        )
    return 0


def _bench_live(args: argparse.Namespace) -> int:
    from beadsight.checkpoint import load_checkpoint
    from beadsight.cli.options import given
    from beadsight.errors import ConfigError
    from beadsight.live.bench import bench_live

    if args.source is not None:
        if args.frames is not None or args.rate is not None:
            raise ConfigError(
                "bench live: --frames and --rate time the predictor alone; "
                "with --source, give --duration (and --fps) instead"
            )
        return _bench_source(args)
    if args.tiers:
        return _bench_tiers(args)
    if args.reference is not None:
        raise ConfigError("bench live: --reference goes with --tiers")
    model = load_checkpoint(args.checkpoint) if args.checkpoint else None
    options = given(frames=args.frames, rate_hz=args.rate, seed=args.seed)
    if options.get("rate_hz") == 0:
        options["rate_hz"] = None  # 0: no sustained run
    result = bench_live(
        model,
        backend=args.backend,
        precision=args.precision,
        device=args.device,
        backend_options=_backend_options(args),
        **options,
    )
    print(json.dumps(result.to_dict()) if args.json else result.summary())
    return 0


def _bench_tiers(args: argparse.Namespace) -> int:
    from beadsight.assets import shipped_model_path
    from beadsight.checkpoint import load_checkpoint
    from beadsight.live.bench import DEFAULT_RATE_HZ, random_model
    from beadsight.live.tiers import TIER_FRAMES, bench_tiers, tiers_summary

    if args.rate is not None and not args.rate > 0:
        from beadsight.errors import ConfigError

        raise ConfigError(f"bench live --tiers: --rate must be > 0 Hz, got {args.rate:g}")
    shipped = load_checkpoint(args.checkpoint or shipped_model_path())
    reference = load_checkpoint(args.reference) if args.reference else random_model(args.seed or 0)
    models = {"reference": reference, "shipped": shipped}
    options = _backend_options(args)
    result = bench_tiers(
        models,
        args.frames or TIER_FRAMES,
        options["cache_dir"],
        options["threads"],
        rate_hz=args.rate or DEFAULT_RATE_HZ,
    )
    print(json.dumps(result) if args.json else tiers_summary(result))
    return 0


def _bench_source(args: argparse.Namespace) -> int:
    from beadsight.cli.options import given
    from beadsight.inference.machine import cpu_summary
    from beadsight.live.bench import bench_source, stats_json
    from beadsight.live.settings import LiveSettings

    settings = LiveSettings(
        source_fps=args.fps,
        **given(backend=args.backend, precision=args.precision, seed=args.seed),
    )
    stats = bench_source(args.checkpoint, args.source, args.duration, settings)
    if args.json:
        print(json.dumps(stats_json(stats, source=args.source, duration_s=args.duration)))
    else:
        print(cpu_summary())
        print(f"source {args.source}, {args.duration:g} s: {stats.summary()}")
    return 0
