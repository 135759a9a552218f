"""Simulator commands: ``beadsight simulate`` and ``beadsight demo``.

Their options are made from :class:`~beadsight.sim.config.SimConfig` and
:class:`~beadsight.demo.config.DemoConfig` fields (defaults included), from the tables
below.
"""

from __future__ import annotations

import argparse

# simulate: flag -> SimConfig field, help
SIMULATE_SIM_FLAGS = (
    ("n_beads", "beads in the pouch; 75, 100 and 125 are the presets", {"flag": "--beads"}),
    ("image_size_px", "frame side in pixels", {"flag": "--image-size"}),
    ("fps", "camera frame rate"),
)
# demo: DemoConfig field, help (every field is an option)
DEMO_FLAGS = (
    ("out", "report folder"),
    ("checkpoint", "a checkpoint instead of the shipped model"),
    ("presses", "held-out presses to simulate"),
    ("pouches", "new pouches the presses are spread over"),
    ("seed", "seed of the held-out presses"),
    ("beads", "beads in the simulated pouch (default: the model's training pouch)", {"type": int}),
    ("max_frames", "frames evaluated, spread evenly (0: all)"),
    ("batch_size", "frames per batch"),
    ("device", "auto, cpu, cuda, ..."),
    ("keep_data", "delete the simulated datasets (heldout.h5, train.h5) when done"),
    ("animation_frames", "consecutive frames in animation.gif"),
    ("progress", "no progress bars"),
    ("train", "train a small model from scratch first"),
    ("train_presses", "simulated training presses (--train)"),
    ("train_pouches", "pouches the training presses are spread over"),
    ("train_steps", "optimizer steps of the small model"),
    ("train_batch_size", "its batch size"),
    ("train_width", "its U-Net width"),
    ("train_image_size", "its image size, px (a multiple of 8)"),
)


def register(commands) -> None:
    commands.add("simulate", _simulate, _simulate_arguments)
    commands.add("demo", _demo, _demo_arguments)


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_fields
    from beadsight.sim.config import LOOK_SPLITS, PRESS_PROFILES, SimConfig

    p.add_argument("--out", required=True, help="output dataset .h5")
    p.add_argument("--presses", type=int, required=True, help="number of presses")
    p.add_argument("--seed", type=int, default=None, help="random seed of the session")
    add_fields(p, SimConfig, SIMULATE_SIM_FLAGS)
    p.add_argument(
        "--compression",
        choices=("gzip", "lzf", "none"),
        default="gzip",
        help="HDF5 compression of the frames: gzip (the default) writes about 12%% less than "
        "none, lzf 3%% less (measured on simulated frames, whose sensor noise compresses "
        "little)",
    )
    p.add_argument(
        "--pouches",
        type=int,
        default=None,
        help="spread the presses over this many fresh pouches (default one; use several "
        "for training sets, so a model does not learn one pouch)",
    )
    p.add_argument(
        "--variety",
        choices=("train", "heldout"),
        default=None,
        help="make every pouch a different build (beads, light, camera, image) drawn from "
        "this split of the range of real builds (docs/simulator.md); with --pouches N, "
        "a base-model training set (train) or builds no base model saw (heldout)",
    )
    p.add_argument(
        "--looks",
        choices=(*LOOK_SPLITS, *(f for families in LOOK_SPLITS.values() for f in families)),
        default=None,
        help="give every pouch a look (beads, background, light, camera) drawn from a "
        "family of this split, or this one family (docs/simulator.md); 'heldout' families "
        "are the foreign-look benchmark: never train on them (default: the reference look)",
    )
    p.add_argument(
        "--profile",
        choices=PRESS_PROFILES,
        default="reference",
        help="how the presses move: reference (F200 descent, 1 s dwell, F700 rise) or "
        "mixed (also 3-20 s and 60-90 s holds, F20-F60 ramps, depth steps and slow drifts "
        "while held; about 2.5x the frames per press), for rest-referenced training",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="simulate in this many processes, each a shard of whole pouches with its own "
        "seed drawn from --seed, joined into --out (needs --pouches >= 2; default 1)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _simulate(args: argparse.Namespace) -> int:
    """Simulate calibration presses on a virtual BeadSight and write a dataset.

    Runs the reference press pattern (F200 descent, 1 s dwell, F700 rise), or with
    --profile mixed also long holds, slow ramps and presses that change while held, on
    the simulated sensor and records frames, the simulated scale's force and the
    commanded printer position, like a real calibration session.
    """
    from beadsight.cli.options import given
    from beadsight.sim.dataset import simulate_dataset

    out = simulate_dataset(
        args.out,
        args.presses,
        n_beads=args.n_beads,
        image_size=args.image_size_px,
        fps=args.fps,
        compression=None if args.compression == "none" else args.compression,
        variety=args.variety,
        profile=args.profile,
        overwrite=args.overwrite,
        progress=not args.no_progress,
        workers=args.workers,
        looks=args.looks,
        **given(seed=args.seed, pouches=args.pouches),
    )
    print(f"wrote {out}")
    return 0


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.cli.options import add_fields
    from beadsight.demo.config import DemoConfig

    add_fields(p, DemoConfig, DEMO_FLAGS)


def _demo(args: argparse.Namespace) -> int:
    """The shipped model on held-out simulated presses: metrics, plots, animation.

    Simulates presses the shipped model never saw, runs it, evaluates it against the
    paper's metrics and two baselines, and writes a report folder (index.html,
    metrics.json, plots, animation.gif). --train trains a small model from scratch
    first and says how long a full run would take.
    """
    from beadsight.cli.options import field_values
    from beadsight.demo.config import DemoConfig
    from beadsight.demo.run import run_demo

    values = field_values(args, DemoConfig)
    values["max_frames"] = values["max_frames"] or None  # 0: all frames
    summary = run_demo(DemoConfig(**values))
    print(summary["description"])
    print()
    print(summary["table"])
    print()
    for note in summary["notes"]:
        print(f"- {note}")
    total = summary["timings_s"]["total_s"]
    print(f"\nreport: {args.out}/index.html ({total:.0f} s)")
    return 0
