"""Choosing a runtime: by name, from an exported file, or automatically (``"auto"``).

:func:`create_backend` is the one entry point: it builds the backend asked for and
refuses it with :class:`~beadsight.inference.parity.ParityError` if it disagrees with
fp32 torch.

``backend="auto"`` (:func:`select_backend`) builds each candidate available here,
drops those that fail parity, times the rest on the probe and keeps the fastest. A
bf16 candidate must stay within half the bound
(:data:`AUTO_REDUCED_PRECISION_MARGIN`): the probes cannot cover every input, and
reduced-precision error varies with the input more than fp32 rounding does. The
decision is cached per checkpoint fingerprint and machine in
``cache_dir/backend-choice.json``; on a cache hit only the chosen backend is built
(and parity-checked again).

The ``int8`` runtime (:mod:`beadsight.inference.int8`) is judged on the paper's metrics
instead (:mod:`beadsight.inference.metric_parity`: every metric within 2 % relative of
fp32 torch on held-out simulated presses): named, it is refused with
:class:`~beadsight.inference.metric_parity.MetricParityError` when it fails; auto
selection tries it first (with OpenVINO and NNCF installed) and drops it when it fails.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from beadsight.checkpoint import PressureModel
from beadsight.errors import ConfigError
from beadsight.files import atomic_write_json
from beadsight.inference.config import INT8
from beadsight.inference.export_format import (
    PRECISION_KEY,
    check_exported_matches,
    model_fingerprint,
)
from beadsight.inference.int8 import Int8Backend, gated_int8, judged_int8
from beadsight.inference.machine import default_cache_dir, importable, machine_key
from beadsight.inference.metric_parity import MetricParityError
from beadsight.inference.parity import (
    PARITY_TOLERANCE,
    check_parity,
    peak_index,
    probe_windows,
    require_parity,
)
from beadsight.inference.planes import GRAPH_VERSION
from beadsight.inference.runtimes import (
    BACKENDS,
    PRECISIONS,
    Backend,
    BackendUnavailableError,
    CudaGraphBackend,
    OnnxBackend,
    OpenVinoBackend,
    TorchBackend,
)

log = logging.getLogger(__name__)

INT8_CANDIDATE = ("int8", INT8)  # tried first on CPUs where openvino and nncf import
CPU_AUTO_ORDER = (("openvino", "bf16"), ("openvino", "fp32"), ("onnx", "fp32"), ("torch", "fp32"))
CPU_FALLBACK_ORDER = (("torch", "fp32"),)  # without OpenVINO/ONNX Runtime
CUDA_AUTO_ORDER = (("cuda", "bf16"), ("cuda", "fp32"))
AUTO_WARMUP_RUNS = 2  # untimed runs before timing a candidate
AUTO_TIMED_RUNS = 5  # timed runs per candidate; the median decides
AUTO_REDUCED_PRECISION_MARGIN = 0.5  # auto takes bf16 only within half the parity bound
CHOICE_FILE = "backend-choice.json"


@dataclass(frozen=True)
class Candidate:
    """One backend tried by :func:`select_backend`."""

    backend: str
    precision: str
    seconds: float | None  # median run time on the probe; None if unusable
    note: str  # parity result or why it was skipped
    err_pct: float | None = None  # worst parity error, % of max(peak, floor)


def _check_precision(precision: str) -> None:
    if precision not in ("auto", *PRECISIONS, INT8):
        raise ConfigError(
            f"precision must be 'auto' or one of {(*PRECISIONS, INT8)}, got {precision!r}"
        )


def _wants_cuda(device: str | torch.device | None) -> bool:
    if device is None:
        return torch.cuda.is_available()
    return torch.device(device).type == "cuda"


def auto_candidates(precision: str = "auto", device: Any = None) -> list[tuple[str, str]]:
    """(backend, precision) pairs ``auto`` tries here, expected-fastest first."""
    if _wants_cuda(device):
        order = list(CUDA_AUTO_ORDER)
    else:
        have_fast = any(importable(m) for m in ("openvino", "onnxruntime"))
        order = list(CPU_AUTO_ORDER if have_fast else CPU_FALLBACK_ORDER)
        if importable("openvino") and importable("nncf"):
            order.insert(0, INT8_CANDIDATE)
    if precision != "auto":
        order = [c for c in order if c[1] == precision]
    return order


def time_backend(backend: Backend, images: np.ndarray, runs: int = AUTO_TIMED_RUNS) -> float:
    """Median seconds per streaming step (one new frame, as live sensing calls it) on
    ``images`` ((1, inputs, S, S, 3), as ``run`` takes them), after
    :data:`AUTO_WARMUP_RUNS` warm-ups."""
    rest = images[0, 0] if backend.rest else None
    window = np.ascontiguousarray(images[:, backend.rest :])
    backend.run_incremental(window, backend.span, rest)
    for _ in range(AUTO_WARMUP_RUNS):
        backend.run_incremental(window, 1, rest)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        backend.run_incremental(window, 1, rest)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def build_backend(
    model: PressureModel,
    name: str,
    precision: str = "fp32",
    device: str | torch.device | None = None,
    exported_model: str | Path | None = None,
    cache_dir: Path | None = None,
    threads: int | None = None,
) -> Backend:
    """Construct backend ``name`` without any parity check (see
    :func:`beadsight.inference.select.create_backend`)."""
    if name not in BACKENDS:
        raise ConfigError(f"backend must be 'auto' or one of {BACKENDS}, got {name!r}")
    if exported_model is not None and name not in ("onnx", "openvino"):
        raise ConfigError(f"exported_model needs backend 'onnx' or 'openvino', not {name!r}")
    if name == "int8":
        return Int8Backend(model, INT8, cache_dir=cache_dir, threads=threads)
    if name == "torch":
        return TorchBackend(model, precision, device=device, threads=threads)
    if name == "onnx":
        return OnnxBackend(model, precision, exported_model, cache_dir, threads)
    if name == "openvino":
        return OpenVinoBackend(model, precision, exported_model, cache_dir, threads)
    return CudaGraphBackend(model, precision, device=device)


# --- the choice cache ---------------------------------------------------------------
def _choice_key(model: PressureModel, precision: str, device: Any) -> str:
    return f"{model_fingerprint(model)[:24]}|{machine_key()}|{precision}|{device}|{GRAPH_VERSION}"


def _read_choices(cache_dir: Path | None) -> dict[str, Any]:
    if not cache_dir:
        return {}
    try:
        return json.loads((Path(cache_dir) / CHOICE_FILE).read_text())
    except (OSError, ValueError):
        return {}


def _write_choice(cache_dir: Path | None, key: str, choice: dict[str, Any]) -> None:
    if cache_dir:
        choices = _read_choices(cache_dir)
        choices[key] = choice
        atomic_write_json(Path(cache_dir) / CHOICE_FILE, choices)


# --- auto selection -----------------------------------------------------------------
@dataclass
class _Probe:
    """The probe windows, their fp32 torch maps, and the window timing runs on."""

    windows: np.ndarray  # (K, inputs, S, S, 3) uint8 RGB
    expected: np.ndarray  # (K, S, S) float32 kPa

    @classmethod
    def of(cls, model: PressureModel) -> _Probe:
        windows = probe_windows(model)
        return cls(windows, model.predict(windows, batch_size=1))

    @property
    def timing_window(self) -> np.ndarray:
        return self.windows[peak_index(self.expected)][None]


def _try_candidate(model, name, precision, device, cache_dir, threads, probe: _Probe):
    """A parity-checked backend, or a string saying why it cannot be used."""
    try:
        if name == "int8":  # judged on the paper's metrics, not pixel by pixel
            return gated_int8(model, cache_dir, threads)
        backend = build_backend(model, name, precision, device, None, cache_dir, threads)
    except MetricParityError as e:
        log.info("auto: %s/%s rejected: %s", name, precision, e)
        return f"rejected, {e}"
    except (BackendUnavailableError, ImportError, RuntimeError) as e:
        log.debug("auto: %s/%s unavailable: %s", name, precision, e)
        return f"unavailable ({e})"
    tolerance = PARITY_TOLERANCE
    if precision != "fp32":  # probes cannot cover every input: demand a margin
        tolerance = replace(tolerance, fraction=tolerance.fraction * AUTO_REDUCED_PRECISION_MARGIN)
    parity = check_parity(backend, model, probe.windows, probe.expected, tolerance)
    if not parity.ok:
        backend.close()
        log.info("auto: %s rejected: %s", backend.describe(), parity)
        return f"rejected, {parity}"
    backend.parity = parity
    return backend


def _cached_choice(model, todo, key, device, cache_dir, threads, probe) -> Backend | None:
    """The backend of a cached decision, if it is still a candidate and still agrees."""
    cached = _read_choices(cache_dir).get(key)
    if not cached or (cached["backend"], cached["precision"]) not in todo:
        return None
    backend = _try_candidate(
        model, cached["backend"], cached["precision"], device, cache_dir, threads, probe
    )
    if not isinstance(backend, Backend):
        return None
    log.info("auto: %s (cached decision)", backend.describe())
    known = set(Candidate.__dataclass_fields__)
    backend.selection = [
        Candidate(**{k: v for k, v in c.items() if k in known})
        for c in cached.get("candidates", [])
    ]
    return backend


def _fastest(model, todo, device, cache_dir, threads, probe) -> tuple[Backend | None, list]:
    """Build, check and time every candidate; the fastest that agrees, and what was tried."""
    best: Backend | None = None
    best_time = float("inf")
    tried: list[Candidate] = []
    for name, prec in todo:
        backend = _try_candidate(model, name, prec, device, cache_dir, threads, probe)
        if not isinstance(backend, Backend):
            tried.append(Candidate(name, prec, None, backend))
            continue
        seconds = time_backend(backend, probe.timing_window)
        parity = backend.parity
        err = getattr(parity, "max_abs_err_pct", None)  # None: judged on metrics (int8)
        tried.append(Candidate(name, prec, seconds, str(parity), err))
        log.info("auto: %s %.1f ms", backend.describe(), seconds * 1e3)
        if seconds < best_time:
            if best is not None:
                best.close()
            best, best_time = backend, seconds
        else:
            backend.close()
    return best, tried


def select_backend(
    model: PressureModel,
    precision: str = "auto",
    device: str | torch.device | None = None,
    cache_dir: Path | None = None,
    threads: int | None = None,
    candidates: list[tuple[str, str]] | None = None,
) -> Backend:
    """The fastest candidate whose output agrees with fp32 torch (see module docs).

    The chosen backend has ``.selection`` (list of :class:`Candidate`) and
    ``.parity`` (:class:`~beadsight.inference.parity.ParityResult`) attributes.
    """
    _check_precision(precision)
    todo = candidates or auto_candidates(precision, device)
    if not todo:
        raise BackendUnavailableError(f"auto: no backend runs {precision} on this machine")
    probe = _Probe.of(model)
    key = _choice_key(model, precision, device)
    cached = _cached_choice(model, todo, key, device, cache_dir, threads, probe)
    if cached is not None:
        return cached
    best, tried = _fastest(model, todo, device, cache_dir, threads, probe)
    if best is None:
        raise BackendUnavailableError(
            "auto: no backend both runs here and agrees with torch: "
            + "; ".join(f"{c.backend}/{c.precision}: {c.note}" for c in tried)
        )
    best.selection = tried
    choice = {
        "backend": best.name,
        "precision": best.precision,
        "candidates": [asdict(c) for c in tried],
        "created_unix_s": time.time(),
    }
    _write_choice(cache_dir, key, choice)
    log.info("auto: chose %s", best.describe())
    return best


# --- the entry point ----------------------------------------------------------------
def create_backend(
    model: PressureModel,
    backend: str = "auto",
    precision: str = "auto",
    device: str | torch.device | None = None,
    exported_model: str | Path | None = None,
    cache_dir: Path | None | str = "default",
    threads: int | None = None,
    check: bool = True,
) -> Backend:
    """A ready backend for ``model``; refused with ``ParityError`` if it disagrees.

    backend: "auto" or one of :data:`~beadsight.inference.runtimes.BACKENDS`.
    precision: "fp32", "bf16", or "auto" (auto selection chooses; a named backend uses
    fp32, or the precision an exported file was made for). exported_model: a ``.onnx``
    or OpenVINO ``.xml`` file made by :func:`beadsight.inference.export.export_model`
    from this checkpoint (refused with
    :class:`~beadsight.inference.export_format.ExportError` if it was made from another);
    with backend "auto" the format picks the backend. cache_dir: "default" ->
    :func:`~beadsight.inference.machine.default_cache_dir`, None -> no disk cache.
    check=False: nothing is refused (what ``evaluate`` runs: scoring it is the check);
    int8 still runs the recipe its metric gate picks, as live sensing would.
    """
    cache = default_cache_dir() if cache_dir == "default" else cache_dir
    cache = Path(cache) if cache else None
    if exported_model is not None:
        return open_exported(exported_model, model, backend, precision, threads, check)
    if backend == "auto":
        return select_backend(model, precision, device, cache, threads)
    _check_precision(precision)
    prec = ("fp32" if backend != "int8" else INT8) if precision == "auto" else precision
    if backend == "int8" and prec == INT8:  # the recipe the metric gate picks
        return gated_int8(model, cache, threads) if check else judged_int8(model, cache, threads)
    result = build_backend(model, backend, prec, device, None, cache, threads)
    if check and not (backend == "torch" and prec == "fp32"):
        require_parity(result, model)
    return result


def open_exported(
    path: str | Path,
    model: PressureModel,
    backend: str = "auto",
    precision: str = "auto",
    threads: int | None = None,
    check: bool = True,
) -> Backend:
    """Run an exported ``.onnx`` / ``.xml`` file, after checking it belongs to ``model``."""
    path = Path(path)
    meta = check_exported_matches(path, model)
    if backend == "auto":
        backend = "openvino" if path.suffix == ".xml" else "onnx"
    if backend not in ("onnx", "openvino"):
        raise ConfigError(f"{path}: exported models run on 'onnx' or 'openvino', not {backend!r}")
    if backend == "onnx" and path.suffix != ".onnx":
        raise ConfigError(f"{path}: onnxruntime runs .onnx files; use backend 'openvino'")
    prec = meta.get(PRECISION_KEY, "fp32") if precision == "auto" else precision
    result = build_backend(model, backend, prec, None, path, None, threads)
    if check:
        require_parity(result, model)
    return result
