"""Simulator commands: ``beadsight simulate`` (and ``beadsight demo``)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate calibration presses on a virtual BeadSight and write a dataset",
        description="Runs the reference press pattern (F200 descent, 1 s dwell, F700 rise) on "
        "the simulated sensor and records frames, the simulated scale's force and the "
        "commanded printer position, like a real calibration session.",
    )
    p.add_argument("--out", required=True, help="output dataset .h5")
    p.add_argument("--presses", type=int, required=True, help="number of presses")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--beads",
        type=int,
        default=100,
        help="beads in the pouch; 75, 100 and 125 are the presets (default 100)",
    )
    p.add_argument("--image-size", type=int, default=256, help="frame side in pixels (256)")
    p.add_argument("--fps", type=float, default=30.0, help="camera frame rate (30)")
    p.add_argument(
        "--compression",
        choices=("gzip", "lzf"),
        default=None,
        help="HDF5 compression of the frames (default none)",
    )
    p.add_argument(
        "--pouches",
        type=int,
        default=1,
        help="spread the presses over this many fresh pouches (default 1; use several "
        "for training sets, so a model does not learn one pouch)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_simulate)
    register_demo(sub)


def _simulate(args: argparse.Namespace) -> int:
    from beadsight.sim.dataset import simulate_dataset

    out = simulate_dataset(
        args.out,
        args.presses,
        seed=args.seed,
        n_beads=args.beads,
        image_size=args.image_size,
        fps=args.fps,
        compression=args.compression,
        pouches=args.pouches,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(f"wrote {out}")
    return 0


def register_demo(sub: argparse._SubParsersAction) -> None:
    from beadsight.demo import DEFAULT_OUT, DemoConfig

    d = DemoConfig()
    p = sub.add_parser(
        "demo",
        help="the shipped model on held-out simulated presses: metrics, plots, animation",
        description="Simulates presses the shipped model never saw, runs it, evaluates it "
        "against the paper's metrics and two baselines, and writes a report folder "
        "(index.html, metrics.json, plots, animation.gif). --train trains a small model "
        "from scratch first and says how long a full run would take.",
    )
    p.add_argument("--out", default=DEFAULT_OUT, help=f"report folder (default ./{DEFAULT_OUT})")
    p.add_argument("--checkpoint", default=None, help="a checkpoint instead of the shipped model")
    p.add_argument("--presses", type=int, default=d.presses, help="held-out presses to simulate")
    p.add_argument(
        "--pouches", type=int, default=d.pouches, help="new pouches the presses are spread over"
    )
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the held-out presses")
    p.add_argument("--beads", type=int, default=None, help="beads in the simulated pouch")
    p.add_argument(
        "--max-frames",
        type=int,
        default=d.max_frames,
        help=f"frames evaluated, spread evenly (default {d.max_frames}; 0: all)",
    )
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--device", default=d.device, help="auto, cpu, cuda, ...")
    p.add_argument("--keep-data", action="store_true", help="keep the simulated dataset(s)")
    p.add_argument(
        "--animation-frames",
        type=int,
        default=d.animation_frames,
        help=f"consecutive frames in animation.gif (default {d.animation_frames})",
    )
    p.add_argument("--train", action="store_true", help="train a small model from scratch first")
    p.add_argument("--train-presses", type=int, default=d.train_presses)
    p.add_argument("--train-pouches", type=int, default=d.train_pouches)
    p.add_argument("--train-steps", type=int, default=d.train_steps)
    p.add_argument("--train-batch-size", type=int, default=d.train_batch_size)
    p.add_argument("--train-width", type=int, default=d.train_width)
    p.add_argument("--train-image-size", type=int, default=d.train_image_size)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    from beadsight.demo import DemoConfig, run_demo

    config = DemoConfig(
        out=args.out,
        checkpoint=args.checkpoint,
        presses=args.presses,
        pouches=args.pouches,
        seed=args.seed,
        beads=args.beads,
        max_frames=args.max_frames or None,
        batch_size=args.batch_size,
        device=args.device,
        keep_data=args.keep_data,
        animation_frames=args.animation_frames,
        progress=not args.no_progress,
        train=args.train,
        train_presses=args.train_presses,
        train_pouches=args.train_pouches,
        train_steps=args.train_steps,
        train_batch_size=args.train_batch_size,
        train_width=args.train_width,
        train_image_size=args.train_image_size,
    )
    summary = run_demo(config)
    print(summary["description"])
    print()
    print(summary["table"])
    print()
    for note in summary["notes"]:
        print(f"- {note}")
    total = summary["timings_s"]["total_s"]
    print(f"\nreport: {args.out}/index.html ({total:.0f} s)")
    return 0
