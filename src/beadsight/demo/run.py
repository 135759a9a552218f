"""Running the demo: the model on held-out simulated presses (:func:`run_demo`), and
``demo --train``, which first trains a small model from scratch (:func:`run_train_demo`)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from beadsight.assets import shipped_model_path
from beadsight.checkpoint import PressureModel
from beadsight.demo.config import (
    ANIMATION_FILE,
    DEFAULT_TRAIN_FRACTION,
    HELDOUT_FILE,
    MARKER,
    REFERENCE_BATCH,
    REFERENCE_EPOCHS,
    REFERENCE_IMAGE_SIZE,
    REFERENCE_PRESSES,
    REFERENCE_WIDTH,
    TIMING_BATCH,
    TRAIN_DEMO_SEED,
    TRAIN_DEMO_VAL_STRIDE,
    DemoConfig,
    DemoError,
)
from beadsight.demo.report import demo_report, demo_summary, prepare_out_dir
from beadsight.files import atomic_write_json
from beadsight.report.animation import (
    animation_colour_max,
    animation_frames,
    strongest_press,
    write_animation,
)
from beadsight.report.page import write_report
from beadsight.sim.config import PRESET_BEAD_COUNTS, SimConfig

logger = logging.getLogger(__name__)


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
    from beadsight.evaluation.config import EvaluateConfig
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
        settings = EvaluateConfig(
            split="all",
            batch_size=config.batch_size,
            device=config.device,
            max_frames=config.max_frames,
            baselines=True,
            progress=config.progress,
            report=False,
        )
        metrics = evaluate(model, data, settings, out)
        timings["evaluate_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        press = strongest_press(data, model)
        clip = animation_frames(model, data, press, config.batch_size, config.animation_frames)
        write_animation(clip, out / ANIMATION_FILE, sim_config.fps)
        timings["animation_s"] = time.perf_counter() - t0
    finally:
        if not config.keep_data:
            data.unlink(missing_ok=True)
    extra["timings"] = timings
    summary = demo_summary(model, config, sim_config, seed, metrics, press, extra)
    atomic_write_json(out / MARKER, summary, strict=True)
    colour_max = animation_colour_max(clip["gt"], clip["pred"])
    write_report(demo_report(summary, metrics, sim_config, colour_max), out)
    return summary


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
    15 frames): forward, backward and AdamW on random inputs, after one warm-up step."""
    import torch

    from beadsight.config import ModelConfig
    from beadsight.model import UNet

    net = UNet(ModelConfig(width=REFERENCE_WIDTH))
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    s = REFERENCE_IMAGE_SIZE
    x = torch.randn(batch, 3 * ModelConfig().frames, s, s)
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
    from beadsight.train.config import TrainConfig
    from beadsight.train.trainer import train

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
