"""The demo's report folder: ``demo.json`` (what was run) and the report page, built by
:mod:`beadsight.evaluation.report` with the animation of one press first."""

from __future__ import annotations

import time
from pathlib import Path

from beadsight.checkpoint import PressureModel
from beadsight.demo.config import (
    ANIMATION_FILE,
    HELDOUT_FILE,
    INDEX_FILE,
    MARKER,
    DemoConfig,
    DemoError,
)
from beadsight.evaluation.animation import animation_caption
from beadsight.evaluation.report import (
    Figure,
    Report,
    evaluation_figures,
    evaluation_links,
    model_card_for,
)
from beadsight.sim.config import SimConfig


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


def demo_summary(
    model: PressureModel,
    config: DemoConfig,
    sim_config: SimConfig,
    seed: int,
    metrics: dict,
    press: int,
    extra: dict,
) -> dict:
    """What demo.json holds: what was run, on what, the metrics, timings and files."""
    from beadsight.metrics import PAPER_METRICS, format_metrics_table

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


def demo_report(summary: dict, metrics: dict, sim_config: SimConfig, colour_max: float) -> Report:
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
