"""Latency and throughput of the live predictor (``beadsight bench live``).

Frames come from the simulator (:class:`beadsight.sim.SimulatedSession`),
pre-rendered once and cycled, so the measurement is of the predictor, not of
the renderer. Two runs, each through :meth:`PressurePredictor.update`:

* **max throughput**: frames fed back to back (timestamps spaced at the nominal
  frame period): readings per second and per-reading latency;
* **sustained** at ``rate_hz`` (30 Hz): frames become available on a wall-clock
  schedule and the loop always takes the newest one, as the live loop does; a
  slow backend then skips frames (the predictor sees them as dropped). Reports
  the achieved reading rate, the predictor's latency and the age of each
  reading (capture -> reading out).

Accuracy: ``max_abs_err_pct`` is the largest error against fp32 torch, in % of
``max(peak, PARITY_FLOOR_KPA)`` of each window, over the parity probes and a few
stream windows.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.rest import REST_FRAMES, average_rest
from beadsight.data.windows import stream_windows
from beadsight.errors import ConfigError
from beadsight.geometry import disk_pressure_kpa
from beadsight.inference.parity import check_parity, probe_windows
from beadsight.inference.predictor import PredictorSettings, PressurePredictor

if TYPE_CHECKING:
    from beadsight.live.settings import LiveSettings
    from beadsight.live.stats import LiveStats


REFERENCE_MEAN_FORCE_N = 10.0  # typical in-contact force of the reference presses, N
DEFAULT_SOURCE_FRAMES = 300  # distinct frames rendered for a benchmark source (10 s at 30 Hz)
DEFAULT_RATE_HZ = 30.0  # camera rate for the sustained run
ERROR_SAMPLE_WINDOWS = 3  # stream windows compared with fp32 torch
SYNTHETIC_PIXEL_MEAN = (128.0, 110.0, 100.0)  # RGB statistics of the random model's input
SYNTHETIC_PIXEL_STD = (45.0, 40.0, 40.0)


def reference_output_scale_kpa(geometry: SensorGeometry) -> float:
    """The reference's ``avg_pressure`` for a 10 N mean force, in kPa.

    avg_pressure = P(mean force) * (finger disk area / image area): the mean
    pressure over the image of a typical press.
    """
    disk_fraction = math.pi * geometry.finger_radius_mm**2 / geometry.sensor_size_mm**2
    return float(disk_pressure_kpa(REFERENCE_MEAN_FORCE_N, geometry)) * disk_fraction


def random_model(
    image_size: int = 256, frames: int = 15, width: int = 16, seed: int = 0
) -> PressureModel:
    """A randomly initialised model (default: reference size, 504k parameters) whose
    output is scaled like a trained one (:func:`reference_output_scale_kpa`)."""
    geometry = SensorGeometry(image_size_px=image_size)
    meta = CheckpointMeta(
        model=ModelConfig(frames=frames, width=width),
        geometry=geometry,
        pixel_mean=list(SYNTHETIC_PIXEL_MEAN),
        pixel_std=list(SYNTHETIC_PIXEL_STD),
        output_scale_kpa=reference_output_scale_kpa(geometry),
        provenance={"source": "random-init", "seed": seed, "fps": DEFAULT_RATE_HZ},
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return PressureModel.create(meta)


def add_model_arguments(parser: Any) -> None:
    """``--checkpoint`` (a trained model) or ``--image-size``/``--width`` of a random one,
    for the live benchmarks' command lines (see :func:`model_from_arguments`)."""
    parser.add_argument("--checkpoint", default=None, help="checkpoint (default: a random model)")
    parser.add_argument("--image-size", type=int, default=256, help="random model size, px")
    parser.add_argument("--width", type=int, default=16, help="random model U-Net width")


def model_from_arguments(args: Any) -> PressureModel:
    """The checkpoint of ``args.checkpoint``, else :func:`random_model` of its size/width."""
    if args.checkpoint:
        from beadsight.checkpoint import load_checkpoint

        return load_checkpoint(args.checkpoint)
    return random_model(image_size=args.image_size, width=args.width)


def simulated_frames(image_size: int, count: int = DEFAULT_SOURCE_FRAMES, seed: int = 0):
    """(count, S, S, 3) uint8 RGB frames of the simulated sensor, and where they came from.

    Uses :class:`beadsight.sim.SimulatedSession`; where the simulator is not
    installed, textured frames with a moving dark press blob stand in.
    """
    try:
        from beadsight.sim import SimConfig, SimulatedSession
    except ImportError:
        return _synthetic_frames(image_size, count, seed), "synthetic (beadsight.sim unavailable)"
    config = SimConfig(image_size_px=image_size)
    records = itertools.islice(iter(SimulatedSession(config, seed)), count)
    frames = np.stack([np.asarray(r.frame_rgb, dtype=np.uint8) for r in records])
    return frames, f"beadsight.sim.SimulatedSession (seed {seed})"


def _synthetic_frames(image_size: int, count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = image_size
    base = rng.normal(SYNTHETIC_PIXEL_MEAN, SYNTHETIC_PIXEL_STD, size=(s, s, 3))
    rows, cols = np.mgrid[0:s, 0:s] + 0.5
    phase = np.arange(count) / DEFAULT_RATE_HZ
    depth = np.clip(np.sin(2 * np.pi * phase / 4.0), 0.0, None)  # one press every 4 s
    centre = s / 2 + s / 5 * np.stack([np.cos(phase / 2), np.sin(phase / 3)], axis=1)
    out = np.empty((count, s, s, 3), dtype=np.uint8)
    for k in range(count):
        d2 = (rows - centre[k, 0]) ** 2 + (cols - centre[k, 1]) ** 2
        blob = 80.0 * depth[k] * np.exp(-d2 / (2 * (s / 10) ** 2))
        frame = base - blob[..., None] + rng.normal(0, 2, size=base.shape)
        out[k] = np.clip(frame, 0, 255)
    return out


@dataclass
class RunStats:
    """One streaming run: achieved rate and latency percentiles (ms)."""

    readings: int
    hz: float
    p50_ms: float
    p99_ms: float
    max_ms: float
    age_p99_ms: float = float("nan")  # capture -> reading out (sustained run)
    skipped_frames: int = 0  # frames the loop never took (it was busy)
    offered_hz: float | None = None

    @classmethod
    def from_samples(cls, latencies_s, span_s, **extra) -> RunStats:
        lat = np.asarray(latencies_s, dtype=np.float64) * 1e3
        n = len(lat)
        hz = (n - 1) / span_s if n > 1 and span_s > 0 else float("nan")
        if n == 0:
            return cls(0, float("nan"), float("nan"), float("nan"), float("nan"), **extra)
        return cls(
            n,
            float(hz),
            float(np.percentile(lat, 50)),
            float(np.percentile(lat, 99)),
            float(lat.max()),
            **extra,
        )


def run_max_throughput(predictor: PressurePredictor, frames: np.ndarray, count: int) -> RunStats:
    """Feed ``count`` frames (cycled) back to back; nominal timestamps, so no gaps."""
    predictor.reset()
    period = predictor.frame_period_s
    latencies, stamps = [], []
    for k in range(count):
        reading = predictor.update(frames[k % len(frames)], k * period)
        if reading is not None:
            stamps.append(time.perf_counter())
            latencies.append(reading.latency_s)
    span = stamps[-1] - stamps[0] if len(stamps) > 1 else 0.0
    return RunStats.from_samples(latencies, span)


def run_sustained(
    predictor: PressurePredictor, frames: np.ndarray, count: int, rate_hz: float
) -> RunStats:
    """Offer ``count`` frames at ``rate_hz`` on the wall clock; process the newest each time."""
    predictor.reset()
    period = 1.0 / rate_hz
    latencies, ages, stamps = [], [], []
    skipped, next_k = 0, 0
    start = time.perf_counter()
    while next_k < count:
        now = time.perf_counter()
        newest = min(int((now - start) / period), count - 1)
        if newest < next_k:
            time.sleep(max(start + next_k * period - now, 0.0))
            continue
        skipped += newest - next_k
        captured = start + newest * period
        reading = predictor.update(frames[newest % len(frames)], captured)
        if reading is not None:
            out = time.perf_counter()
            stamps.append(out)
            latencies.append(reading.latency_s)
            ages.append(out - captured)
        next_k = newest + 1
    span = stamps[-1] - stamps[0] if len(stamps) > 1 else 0.0
    stats = RunStats.from_samples(latencies, span, skipped_frames=skipped, offered_hz=rate_hz)
    if ages:
        stats.age_p99_ms = float(np.percentile(np.asarray(ages) * 1e3, 99))
    return stats


def max_error_pct(predictor: PressurePredictor, frames: np.ndarray) -> float:
    """Largest error vs fp32 torch, % of max(peak, floor): probes + a few stream windows."""
    model = predictor.model
    t = model.span
    if len(frames) < t:
        return float(check_parity(predictor.backend, model).max_abs_err_pct)
    ends = np.unique(np.linspace(t - 1, len(frames) - 1, ERROR_SAMPLE_WINDOWS).astype(int))
    # against the rest image the predictor took: its first frames
    rest = average_rest(frames[:REST_FRAMES]) if model.rest else None
    windows = np.concatenate([probe_windows(model), stream_windows(frames, ends, t, rest)])
    return float(check_parity(predictor.backend, model, windows).max_abs_err_pct)


@dataclass
class LiveBenchResult:
    """``beadsight bench live`` figures; :meth:`to_dict` is its ``--json`` output."""

    backend: str
    frames: int
    max_abs_err_pct: float
    throughput: RunStats
    sustained: RunStats | None
    source: str
    model: dict[str, Any] = field(default_factory=dict)
    selection: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        t = self.throughput
        out = {
            "backend": self.backend,
            "hz": t.hz,
            "p50_ms": t.p50_ms,
            "p99_ms": t.p99_ms,
            "max_ms": t.max_ms,
            "max_abs_err_pct": self.max_abs_err_pct,
            "frames": self.frames,
            "throughput": asdict(t),
            "sustained": asdict(self.sustained) if self.sustained else None,
            "source": self.source,
            "model": self.model,
            "auto_selection": self.selection,
        }
        return {k: json_safe(v) for k, v in out.items()}

    def summary(self) -> str:
        t = self.throughput
        lines = [
            f"backend {self.backend}; model {self.model}; frames from {self.source}",
            f"max throughput : {t.hz:7.1f} readings/s   latency p50 {t.p50_ms:6.1f} ms  "
            f"p99 {t.p99_ms:6.1f} ms  max {t.max_ms:6.1f} ms",
        ]
        if self.sustained is not None:
            s = self.sustained
            lines.append(
                f"sustained {s.offered_hz:g} Hz: {s.hz:7.1f} readings/s   latency p50 "
                f"{s.p50_ms:6.1f} ms  p99 {s.p99_ms:6.1f} ms  max {s.max_ms:6.1f} ms  "
                f"(age p99 {s.age_p99_ms:.1f} ms, {s.skipped_frames} frames skipped)"
            )
        lines.append(f"max error vs fp32 torch: {self.max_abs_err_pct:.3g} % of peak")
        return "\n".join(lines)


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float (in dicts and lists too) as None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [json_safe(v) for v in value]
    return value


def bench_live(
    model: PressureModel | None = None,
    backend: str = "auto",
    precision: str = "auto",
    frames: int = 600,
    rate_hz: float | None = DEFAULT_RATE_HZ,
    device: str | None = None,
    backend_options: dict[str, Any] | None = None,
    source_frames: np.ndarray | None = None,
    seed: int = 0,
) -> LiveBenchResult:
    """Measure a predictor on simulated frames (see the module docstring).

    model: None -> :func:`random_model` (reference size). frames: frames per run.
    rate_hz: the sustained run's camera rate; None or 0 skips it.
    """
    model = model if model is not None else random_model(seed=seed)
    if frames < model.span + 1:
        raise ConfigError(f"frames must be > the span ({model.span}), got {frames}")
    if source_frames is None:
        count = min(frames, DEFAULT_SOURCE_FRAMES)
        source_frames, source = simulated_frames(model.image_size, count, seed)
    else:
        source = "given frames"
    predictor = PressurePredictor.from_checkpoint(
        model,
        backend,
        precision,
        device,
        **(backend_options or {}),
        settings=PredictorSettings(on_gap="ignore"),
    )
    try:
        throughput = run_max_throughput(predictor, source_frames, frames)
        sustained = run_sustained(predictor, source_frames, frames, rate_hz) if rate_hz else None
        err = max_error_pct(predictor, source_frames)
        selection = [asdict(c) for c in getattr(predictor.backend, "selection", [])]
        return LiveBenchResult(
            backend=predictor.backend.describe(),
            frames=frames,
            max_abs_err_pct=err,
            throughput=throughput,
            sustained=sustained,
            source=source,
            model={
                "image_size": model.image_size,
                "frames": model.frames,
                "span": model.span,
                "width": model.meta.model.width,
                "parameters": sum(p.numel() for p in model.module.net.parameters()),
                "checkpoint": model.source,
            },
            selection=selection,
        )
    finally:
        predictor.close()


def bench_source(
    checkpoint: Any,
    source: Any,
    duration_s: float = 10.0,
    settings: LiveSettings | None = None,
) -> LiveStats:
    """Run the live loop on ``source`` (camera index or path, video file, ``"sim"``) for
    ``duration_s`` and return its :class:`~beadsight.live.stats.LiveStats`: readings/s,
    camera-to-reading latency, and the camera's truth (delivered fps against the rate
    asked, dropped and duplicated frames, ``camera_slow``)."""
    from beadsight.live.sensor import LiveSensor

    if not duration_s > 0:
        raise ConfigError(f"duration must be > 0 s, got {duration_s!r}")
    with LiveSensor(checkpoint, source, settings=settings) as sensor:
        sensor.wait(duration_s)
        stats = sensor.stats()
        error = sensor.error
    if error is not None:
        raise error
    return stats


def stats_json(stats: LiveStats, **extra: Any) -> dict[str, Any]:
    """A LiveStats as a JSON-safe dict (NaN -> None), with ``extra`` keys first."""
    return {**extra, **json_safe(asdict(stats))}
