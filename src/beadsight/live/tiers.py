"""The runtime tiers (``beadsight bench live --tiers``): eager torch fp32, the best fp32
runtime and int8, one after another on this CPU, for each model given.

Each tier runs through :class:`~beadsight.inference.predictor.PressurePredictor` on the
simulated frames of :mod:`beadsight.live.bench`: readings/s and p50/p99 latency flat out,
whether a 30 Hz camera is held (every frame read, each reading out within a frame
period), and the paper's metrics on the metric gate's held-out simulated presses with
their change from fp32 torch (for int8, the recipe its gate picks and its verdict).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.inference.predictor import PredictorSettings, PressurePredictor
from beadsight.live.bench import (
    DEFAULT_RATE_HZ,
    DEFAULT_SOURCE_FRAMES,
    json_safe,
    run_max_throughput,
    run_sustained,
    simulated_frames,
)

log = logging.getLogger(__name__)

TIER_FRAMES = 300  # frames per throughput run of each tier


def _tier_backends(model: PressureModel, cache_dir: Any, threads: int | None, presses, reference):
    """(tier, build) pairs: eager torch fp32, the fastest fp32 runtime that agrees with
    it (auto selection among the others), and int8 by the recipe its gate picks (timed
    even when every recipe is refused: the gate's figures are reported beside it)."""
    from beadsight.inference.int8 import judged_int8
    from beadsight.inference.select import auto_candidates, build_backend, select_backend

    others = [c for c in auto_candidates("fp32") if c[0] != "torch"]
    cache = None if cache_dir in (None, "none") else cache_dir
    if cache == "default":
        from beadsight.inference.machine import default_cache_dir

        cache = default_cache_dir()
    return (
        ("eager torch fp32", lambda: build_backend(model, "torch", "fp32", threads=threads)),
        (
            "best fp32",
            lambda: select_backend(model, "fp32", None, cache, threads, candidates=others),
        ),
        ("int8", lambda: judged_int8(model, cache, threads, presses=presses, reference=reference)),
    )


def bench_tier(
    model: PressureModel,
    backend,
    frames: np.ndarray,
    count: int,
    presses,
    reference,
    rate_hz: float = DEFAULT_RATE_HZ,
) -> dict:
    """One runtime: max throughput through the predictor, ``count`` frames offered at
    ``rate_hz`` (the camera: is the rate held, and how old is each reading when it is
    out?) and its metric parity (``reference``: fp32 torch's maps of ``presses``; the
    int8 gate's verdict where it judged the backend on them)."""
    from beadsight.inference.metric_parity import MetricParity, metric_parity

    parity = getattr(backend, "parity", None)  # fp32 runtimes': element-wise
    if not isinstance(parity, MetricParity):
        parity = metric_parity(backend, model, presses, reference=reference)
    predictor = PressurePredictor(model, backend, settings=PredictorSettings(on_gap="ignore"))
    try:
        stats = run_max_throughput(predictor, frames, count)
        held = run_sustained(predictor, frames, count, rate_hz)
    finally:
        predictor.close()
    return {
        "backend": backend.describe(),
        "int8_recipe": getattr(backend, "recipe", None) and backend.recipe.key,
        "readings_per_s": stats.hz,
        "p50_ms": stats.p50_ms,
        "p99_ms": stats.p99_ms,
        "camera": {
            "offered_hz": rate_hz,
            "readings_per_s": held.hz,
            "skipped_frames": held.skipped_frames,
            "age_p99_ms": held.age_p99_ms,  # camera frame -> reading out
            # issue 25's bar: every frame read, each reading out within a frame period
            "held": held.skipped_frames == 0 and held.age_p99_ms <= 1e3 / rate_hz,
        },
        "metric_parity_ok": parity.ok,
        "metrics_meaningful": parity.meaningful,
        "metric_deltas_pct": {k: 100 * v for k, v in parity.deltas.items()},
        "metrics": parity.candidate,
    }


def bench_tiers(
    models: dict[str, PressureModel],
    frames: int = TIER_FRAMES,
    cache_dir: Any = "default",
    threads: int | None = None,
    seed: int = 0,
    rate_hz: float = DEFAULT_RATE_HZ,
) -> dict[str, Any]:
    """For each model: eager torch fp32, the best fp32 runtime and int8, one after another
    on this CPU: readings/s, p50/p99 latency (ms), speedup over eager torch, whether a
    30 Hz camera is held (:func:`bench_tier`), and the paper's metrics on held-out
    simulated presses with their change from fp32 torch."""
    from beadsight.inference.machine import cpu_flags, cpu_name, cpu_summary
    from beadsight.inference.metric_parity import fp32_maps, simulated_presses

    out: dict[str, Any] = {"cpu": cpu_summary(), "cpu_model": cpu_name(), "flags": cpu_flags()}
    for name, model in models.items():
        source, _ = simulated_frames(model.image_size, min(frames, DEFAULT_SOURCE_FRAMES), seed)
        presses = simulated_presses(model)
        reference = fp32_maps(model, presses)
        rows = []
        for tier, build in _tier_backends(model, cache_dir, threads, presses, reference):
            backend = build()
            row = bench_tier(model, backend, source, frames, presses, reference, rate_hz)
            rows.append({"tier": tier, **row})
            log.info("bench tiers: %s %s: %s", name, tier, rows[-1])
        eager = rows[0]["readings_per_s"]
        for row in rows:
            row["speedup_vs_eager"] = row["readings_per_s"] / eager if eager else None
        out[name] = {
            "model": {
                "image_size": model.image_size,
                "frames": model.frames,
                "span": model.span,
                "width": model.meta.model.width,
                "checkpoint": model.source,
            },
            "tiers": rows,
        }
    return json_safe(out)


def tiers_summary(result: dict[str, Any]) -> str:
    """The tiers as a plain-text table, the CPU first."""
    lines = [result["cpu"]]
    for name, entry in result.items():
        if not isinstance(entry, dict) or "tiers" not in entry:
            continue
        m = entry["model"]
        lines.append(f"{name}: {m['image_size']} px, width {m['width']}, {m['frames']} frames")
        for row in entry["tiers"]:
            deltas = ", ".join(
                f"{k} {v:+.2f}%" if v is not None else f"{k} n/a"
                for k, v in row["metric_deltas_pct"].items()
            )
            gate = "passes" if row["metric_parity_ok"] else "fails"
            if row["int8_recipe"]:
                gate += f" (recipe {row['int8_recipe']})"
            cam = row["camera"]
            lines.append(
                f"  {row['tier']:16s} {row['backend']:14s} {row['readings_per_s'] or 0:7.1f}/s "
                f"p50 {row['p50_ms'] or 0:6.1f} ms p99 {row['p99_ms'] or 0:6.1f} ms "
                f"x{row['speedup_vs_eager'] or 0:.2f}; camera {cam['offered_hz']:g} Hz "
                f"{'held' if cam['held'] else 'not held'} ({cam['readings_per_s'] or 0:.1f}/s, "
                f"{cam['skipped_frames']} skipped, age p99 {cam['age_p99_ms'] or 0:.1f} ms); "
                f"metric gate {gate}: {deltas}"
            )
    return "\n".join(lines)
