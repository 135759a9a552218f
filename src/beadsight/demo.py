"""``beadsight demo``: the shipped model on held-out simulated presses, as a report folder.

:func:`run_demo` simulates presses the model never saw (a seed of their own) at
the model's image size, runs the model over them, scores it with
:func:`beadsight.evaluation.evaluate.evaluate` (with the all-zero and mean-label
baselines), and writes a report folder:

* ``metrics.json``, ``predictions.h5`` and the evaluation plots
  (``examples.png``, ``region_error.png``, ``force_traces.png``);
* ``animation.gif``: one press, camera frame | true map | predicted map;
* ``demo.json`` (what was run, seeds, timings) and ``index.html`` (the report).

:func:`run_train_demo` (``beadsight demo --train``) first simulates a small
training set and trains a small model from scratch, then reports it the same
way, with the measured training rate and what a full run would take on this
machine.

The shipped model is ``beadsight/assets/sim_model.pt`` (see ``sim_model.md``
beside it), found with :mod:`importlib.resources`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.checkpoint import PressureModel, shipped_model_path
from beadsight.config import _Serializable
from beadsight.errors import BeadSightError
from beadsight.evaluation.animation import (
    ANIMATION_MAX_FRAMES,
    animation_caption,
    animation_colour_max,
    animation_frames,
    strongest_press,
    write_animation,
)
from beadsight.evaluation.report import (
    Figure,
    Report,
    evaluation_figures,
    evaluation_links,
    model_card_for,
    write_report,
)
from beadsight.files import atomic_write_json
from beadsight.sim.config import PRESET_BEAD_COUNTS, SimConfig

logger = logging.getLogger(__name__)

DEMO_SEED = 90_210  # held-out presses; training sets must use other seeds
TRAIN_DEMO_SEED = 31_337  # the training set of ``demo --train``
DEFAULT_OUT = "beadsight-demo"
MARKER = "demo.json"  # a folder holding this file is a demo report and may be overwritten
HELDOUT_FILE = "heldout.h5"
ANIMATION_FILE = "animation.gif"
INDEX_FILE = "index.html"
# The reference training recipe (reference-facts section 7), for the time estimate.
REFERENCE_PRESSES = 500
REFERENCE_EPOCHS = 100
REFERENCE_BATCH = 64
REFERENCE_IMAGE_SIZE = 256
REFERENCE_WIDTH = 16
TIMING_BATCH = 2  # samples per timed step of the reference-size network
TRAIN_DEMO_VAL_STRIDE = 4  # demo --train validates on every 4th window (time)
DEFAULT_TRAIN_FRACTION = 0.7


class DemoError(BeadSightError):
    """The demo cannot run as asked (missing model, bad folder, bad sizes); says why."""


@dataclass(frozen=True)
class DemoConfig(_Serializable):
    """What ``beadsight demo`` runs. Defaults fit in ~3 minutes on a 2-core CPU."""

    out: str = DEFAULT_OUT  # report folder
    checkpoint: str | None = None  # None: the shipped model
    presses: int = 10  # held-out presses to simulate
    pouches: int = 3  # ... on this many fresh pouches (never seen in training)
    seed: int = DEMO_SEED  # of the held-out presses
    beads: int | None = None  # None: the model's training pouch, else the 100-bead preset
    max_frames: int | None = 800  # frames evaluated, spread evenly over the presses
    batch_size: int = 16
    device: str = "auto"
    keep_data: bool = False  # keep the simulated held-out dataset in the report folder
    animation_frames: int = ANIMATION_MAX_FRAMES  # consecutive frames in animation.gif
    progress: bool = True
    # --- demo --train ---
    train: bool = False
    train_presses: int = 16  # simulated training presses
    train_pouches: int = 4  # ... spread over this many pouches
    train_steps: int = 40  # optimizer steps
    train_batch_size: int = 8
    train_width: int = 8
    train_image_size: int = 64

    def __post_init__(self) -> None:
        for name, low in (
            ("presses", 1),
            ("pouches", 1),
            ("train_pouches", 1),
            ("batch_size", 1),
            ("train_presses", 3),
            ("animation_frames", 1),
            ("train_steps", 1),
            ("train_batch_size", 1),
            ("train_width", 1),
            ("train_image_size", 8),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < low:
                raise DemoError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise DemoError(f"max_frames must be >= 1 or None, got {self.max_frames!r}")


# --- the model ----------------------------------------------------------------------
def training_simulation(model: PressureModel) -> tuple[set[int], dict | None]:
    """Seeds and SimConfig dict of the simulated data a model was trained on, where known.

    Looks at the checkpoint's provenance (``sim: {seed, config}``, which ``beadsight train``
    records for simulated data) and at the training dataset's provenance if that file is here.
    """
    seeds: set[int] = set()
    config = None
    sim = model.meta.provenance.get("sim")
    if isinstance(sim, dict):
        seeds.update(int(s) for s in np.atleast_1d(sim.get("seed", [])).tolist())
        config = sim.get("config")
    path = model.meta.training.get("dataset_path") or model.meta.provenance.get("dataset")
    if path and Path(path).is_file():
        from beadsight.data.dataset import open_dataset

        try:
            with open_dataset(path) as ds:
                prov = ds.provenance.get("simulator") or {}
        except ValueError:
            prov = {}
        if "seed" in prov:
            seeds.add(int(prov["seed"]))
        config = config or prov.get("config")
    return seeds, config


def demo_sim_config(model: PressureModel, beads: int | None, trained_on: dict | None) -> SimConfig:
    """The simulated sensor for held-out presses: the training pouch at the model's size."""
    size = model.image_size
    if beads is None and trained_on:
        base = SimConfig.from_dict(trained_on)
    else:
        n = 100 if beads is None else beads
        base = SimConfig.preset(n) if n in PRESET_BEAD_COUNTS else SimConfig(n_beads=n)
    return dataclasses.replace(base, image_size_px=size)


# --- the report folder ----------------------------------------------------------------
def prepare_out_dir(out: Path) -> None:
    """Create ``out``; refuse a non-empty folder that is not an earlier demo report."""
    if out.exists() and not out.is_dir():
        raise DemoError(f"{out}: exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise DemoError(
            f"{out}: folder exists, is not empty and is not a beadsight demo report "
            f"(no {MARKER}); choose another --out"
        )
    out.mkdir(parents=True, exist_ok=True)


# --- running ------------------------------------------------------------------------
def _simulate(
    config: SimConfig, presses: int, pouches: int, seed: int, path: Path, progress: bool
) -> Path:
    from beadsight.sim.dataset import simulate_dataset

    if path.exists():
        path.unlink()
    return simulate_dataset(
        path, presses, seed=seed, config=config, pouches=min(pouches, presses), progress=progress
    )


def _evaluate_and_report(
    model: PressureModel, config: DemoConfig, sim_config: SimConfig, seed: int, extra: dict
) -> dict:
    """Simulate held-out presses, evaluate, animate, write the report; returns the summary."""
    from beadsight.evaluation.evaluate import evaluate

    out = Path(config.out)
    timings: dict[str, float] = dict(extra.pop("timings", {}))
    t0 = time.perf_counter()
    data = _simulate(
        sim_config, config.presses, config.pouches, seed, out / HELDOUT_FILE, config.progress
    )
    timings["simulate_heldout_s"] = time.perf_counter() - t0
    try:
        t0 = time.perf_counter()
        metrics = evaluate(
            model,
            data,
            split="all",
            out_dir=out,
            batch_size=config.batch_size,
            device=config.device,
            max_frames=config.max_frames,
            baselines=True,
            progress=config.progress,
            report=False,
        )
        timings["evaluate_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        press = strongest_press(data)
        clip = animation_frames(model, data, press, config.batch_size, config.animation_frames)
        write_animation(clip, out / ANIMATION_FILE, sim_config.fps)
        timings["animation_s"] = time.perf_counter() - t0
    finally:
        if not config.keep_data:
            data.unlink(missing_ok=True)
    extra["timings"] = timings
    summary = _summary(model, config, sim_config, seed, metrics, press, extra)
    atomic_write_json(out / MARKER, summary, strict=True)
    colour_max = animation_colour_max(clip["gt"], clip["pred"])
    write_report(_report(summary, metrics, sim_config, colour_max), out)
    return summary


def _summary(
    model: PressureModel,
    config: DemoConfig,
    sim_config: SimConfig,
    seed: int,
    metrics: dict,
    press: int,
    extra: dict,
) -> dict:
    """What demo.json holds: what was run, on what, the metrics, timings and files."""
    from beadsight.evaluation.metrics import PAPER_METRICS, format_metrics_table

    files = dict(
        metrics.get("files", {}), animation=ANIMATION_FILE, report=INDEX_FILE, summary=MARKER
    )
    if config.keep_data:
        files["heldout_dataset"] = HELDOUT_FILE
    which = "The shipped model" if config.checkpoint is None else "The model"
    spread = f", spread evenly over them (--max-frames {config.max_frames})"
    timings = extra.pop("timings")
    card = model_card_for(model.source)
    return {
        "description": (
            f"{which} {model.source} was run on {config.presses} simulated presses it never "
            f"saw, on {min(config.pouches, config.presses)} new pouches (seed {seed}; "
            f"{sim_config.n_beads} beads, {sim_config.image_size_px} px frames at "
            f"{sim_config.fps:g} fps), and scored against the true pressure maps on "
            f"{metrics['frames']} frames{spread if config.max_frames else ''}, beside the "
            f"paper's figures and two baselines. The animation shows press {press}, the "
            "strongest."
        ),
        "demo_config": config.to_dict(),
        "seed": seed,
        "sim_config": sim_config.to_dict(),
        "checkpoint": str(model.source),
        "model_card": str(Path(model.source).with_suffix(".md")) if card else None,
        "metrics": {k: metrics.get(k) for k in PAPER_METRICS},
        "baselines": metrics.get("baselines"),
        "paper": dict(PAPER_METRICS),
        "frames_evaluated": metrics["frames"],
        "animation_press": press,
        "timings_s": {
            **{k: round(v, 2) for k, v in timings.items()},
            "total_s": round(time.perf_counter() - extra.pop("started"), 1),
        },
        "files": files,
        "notes": [
            "The paper's figures are for the real sensor; these are for the simulated one. "
            "Compare the model with the baselines here, and trends rather than digits with "
            "the paper.",
            "Baselines: 'zero' predicts no pressure; 'mean_gt' predicts the mean label of the "
            "evaluated presses (a constant map).",
            *extra.pop("notes", []),
        ],
        **extra,
        "table": format_metrics_table(metrics, metrics.get("baselines")),
    }


def _report(summary: dict, metrics: dict, sim_config: SimConfig, colour_max: float) -> Report:
    """The demo's report page: the evaluation's, with the animation first."""
    files = summary["files"]
    animation = Figure(
        ANIMATION_FILE, "One held-out press", animation_caption(sim_config.fps, colour_max)
    )
    descriptions = {
        "animation": "the animation above (GIF)",
        "summary": "what was run: configuration, seeds, timings, metrics (JSON)",
        "heldout_dataset": "the simulated held-out presses (HDF5 dataset)",
    }
    return Report(
        title="beadsight demo: pressure maps from the simulated sensor",
        summary=summary["description"],
        metrics=metrics,
        baselines=metrics.get("baselines") or {},
        notes=summary["notes"],
        figures=[animation, *evaluation_figures(files, metrics, sim_config.geometry)],
        model_card=model_card_for(summary["checkpoint"]),
        model_card_title=f"Model card ({Path(summary['checkpoint']).with_suffix('.md').name})",
        files=evaluation_links(files, descriptions),
    )


def run_demo(config: DemoConfig = DemoConfig()) -> dict:
    """The shipped (or ``config.checkpoint``) model on held-out simulated presses.

    Returns the summary (also written to ``<out>/demo.json``), with ``table``: the
    metrics beside the paper's figures and the baselines, as printed.
    """
    if config.train:
        return run_train_demo(config)
    from beadsight.evaluation.predict import as_model

    t0 = time.perf_counter()
    path = Path(config.checkpoint) if config.checkpoint else shipped_model_path()
    model = as_model(path, config.device)
    prepare_out_dir(Path(config.out))
    seeds, trained_on = training_simulation(model)
    seed = config.seed
    while seed in seeds:  # never evaluate on presses the model was trained on
        logger.warning("seed %d was used for the model's training data; using %d", seed, seed + 1)
        seed += 1
    sim_config = demo_sim_config(model, config.beads, trained_on)
    extra: dict[str, Any] = {
        "timings": {"load_model_s": time.perf_counter() - t0},
        "started": t0,
    }
    return _evaluate_and_report(model, config, sim_config, seed, extra)


# --- demo --train -------------------------------------------------------------------
def time_reference_step(batch: int = TIMING_BATCH, steps: int = 1) -> float:
    """Seconds per training *sample* of the reference network (256 px, width 16,
    window 15): forward, backward and AdamW on random inputs, after one warm-up step."""
    import torch

    from beadsight.config import ModelConfig
    from beadsight.model import UNet

    net = UNet(ModelConfig(width=REFERENCE_WIDTH))
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    s = REFERENCE_IMAGE_SIZE
    x = torch.randn(batch, 3 * ModelConfig().window, s, s)
    y = torch.rand(batch, 1, s, s)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        torch.nn.functional.mse_loss(net(x), y).backward()
        opt.step()

    step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return (time.perf_counter() - t0) / (steps * batch)


def _train_rate(run: Path) -> tuple[int, float]:
    """(steps, seconds spent on them) from a run's metrics.jsonl: the last training log
    line (validation time excluded), or the last line with a step if there is none."""
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if r.get("step") and r.get("time_s")]
    train_rows = [r for r in rows if r.get("event") == "train"]
    if not rows:
        raise DemoError(f"{run}: the training run logged no steps")
    last = (train_rows or rows)[-1]
    return int(last["step"]), float(last["time_s"])


def full_run_estimate(
    seconds_per_step: float, batch: int, windows_per_press: float, reference_s_per_sample: float
) -> dict:
    """What the reference recipe (500 presses, 70 % train, 100 epochs, batch 64) would take."""
    windows = REFERENCE_PRESSES * DEFAULT_TRAIN_FRACTION * windows_per_press
    steps = REFERENCE_EPOCHS * math.ceil(windows / REFERENCE_BATCH)
    samples = steps * REFERENCE_BATCH
    return {
        "planned_steps": steps,
        "planned_samples": samples,
        "this_size_hours": samples * seconds_per_step / batch / 3600,
        "reference_size_hours": samples * reference_s_per_sample / 3600,
        "reference_s_per_sample": reference_s_per_sample,
    }


def run_train_demo(config: DemoConfig) -> dict:
    """Simulate a small training set, train a small model from scratch, evaluate it."""
    from beadsight.train.trainer import TrainConfig, train

    out = Path(config.out)
    prepare_out_dir(out)
    if config.train_image_size % 8:
        raise DemoError(f"train_image_size must be a multiple of 8, got {config.train_image_size}")
    sim_config = SimConfig.preset(config.beads or 100, image_size_px=config.train_image_size)
    timings: dict[str, float] = {}
    started = t0 = time.perf_counter()
    train_data = _simulate(
        sim_config,
        config.train_presses,
        config.train_pouches,
        TRAIN_DEMO_SEED,
        out / "train.h5",
        config.progress,
    )
    timings["simulate_train_s"] = time.perf_counter() - t0
    run = out / "run"
    try:
        t0 = time.perf_counter()
        train(
            TrainConfig(
                data=str(train_data),
                out=str(run),
                steps=config.train_steps,
                batch_size=config.train_batch_size,
                width=config.train_width,
                device=config.device,
                seed=0,
                progress=config.progress,
                log_every_steps=max(1, config.train_steps // 10),
                val_stride=TRAIN_DEMO_VAL_STRIDE,
                checkpoint_every_min=1e6,
            )
        )
        timings["train_s"] = time.perf_counter() - t0
        steps, seconds = _train_rate(run)
        split = json.loads((run / "split.json").read_text())
        windows_per_press = split["windows"]["train"] / max(len(split["train"]), 1)
    finally:
        if not config.keep_data:
            train_data.unlink(missing_ok=True)
    from beadsight.evaluation.predict import as_model

    model = as_model(run / "best.pt", config.device)
    t0 = time.perf_counter()
    reference = time_reference_step()
    timings["time_reference_step_s"] = time.perf_counter() - t0
    estimate = full_run_estimate(
        seconds / steps, config.train_batch_size, windows_per_press, reference
    )
    estimate.update(measured_steps=steps, measured_s_per_step=seconds / steps)
    note = (
        f"Trained {steps} steps in {seconds:.0f} s ({seconds / steps:.2f} s/step at "
        f"{config.train_image_size} px, width {config.train_width}, batch "
        f"{config.train_batch_size}). A full run with the reference recipe "
        f"({REFERENCE_PRESSES} presses, {REFERENCE_EPOCHS} epochs, batch {REFERENCE_BATCH}: "
        f"{estimate['planned_steps']} steps) would take ~{estimate['this_size_hours']:.1f} h at "
        f"this size, and ~{estimate['reference_size_hours']:.0f} h at {REFERENCE_IMAGE_SIZE} px "
        f"width {REFERENCE_WIDTH} ({reference:.2f} s per sample measured here); use a GPU "
        "(beadsight train --device cuda --precision bf16) for full runs."
    )
    extra = {
        "timings": timings,
        "train_run": "run",
        "full_run_estimate": estimate,
        "notes": [note],
        "started": started,
    }
    demo_cfg = dataclasses.replace(config, checkpoint=str(run / "best.pt"))
    seed = config.seed if config.seed != TRAIN_DEMO_SEED else config.seed + 1
    summary = _evaluate_and_report(model, demo_cfg, sim_config, seed, extra)
    summary["train_note"] = note
    return summary
