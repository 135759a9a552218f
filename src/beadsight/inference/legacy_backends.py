"""The public names of beadsight 0.1's ``beadsight.backends`` module, for one release.

0.1 kept runtimes, parity checks and backend selection in one module; they are now
:mod:`beadsight.inference.runtimes`, :mod:`~beadsight.inference.parity`,
:mod:`~beadsight.inference.select` and :mod:`~beadsight.inference.machine`.
``import beadsight.backends`` (:mod:`beadsight._compat`) gives this module, with a
DeprecationWarning. New code imports from the modules above.
"""

from __future__ import annotations

from beadsight.inference.machine import default_cache_dir, default_threads
from beadsight.inference.parity import (
    PARITY_FLOOR_KPA,
    PARITY_TOLERANCE,
    PROBE_DEPTH_STD,
    PROBE_SEED,
    PROBE_TEXTURE_STD,
    ParityError,
    ParityResult,
    ParityTolerance,
    check_parity,
    probe_window,
    probe_windows,
)
from beadsight.inference.runtimes import (
    BACKENDS,
    PRECISIONS,
    Backend,
    BackendError,
    BackendUnavailableError,
    CompileBackend,
    CudaGraphBackend,
    OnnxBackend,
    OpenVinoBackend,
    TorchBackend,
    build_backend,
    openvino_supports_bf16,
)
from beadsight.inference.select import (
    AUTO_REDUCED_PRECISION_MARGIN,
    AUTO_TIMED_RUNS,
    AUTO_WARMUP_RUNS,
    CHOICE_FILE,
    CPU_AUTO_ORDER,
    CPU_FALLBACK_ORDER,
    CUDA_AUTO_ORDER,
    Candidate,
    auto_candidates,
    create_backend,
    open_exported,
    select_backend,
    time_backend,
)

__all__ = [
    "AUTO_REDUCED_PRECISION_MARGIN",
    "AUTO_TIMED_RUNS",
    "AUTO_WARMUP_RUNS",
    "BACKENDS",
    "CHOICE_FILE",
    "CPU_AUTO_ORDER",
    "CPU_FALLBACK_ORDER",
    "CUDA_AUTO_ORDER",
    "PARITY_FLOOR_KPA",
    "PARITY_TOLERANCE",
    "PRECISIONS",
    "PROBE_DEPTH_STD",
    "PROBE_SEED",
    "PROBE_TEXTURE_STD",
    "Backend",
    "BackendError",
    "BackendUnavailableError",
    "Candidate",
    "CompileBackend",
    "CudaGraphBackend",
    "OnnxBackend",
    "OpenVinoBackend",
    "ParityError",
    "ParityResult",
    "ParityTolerance",
    "TorchBackend",
    "auto_candidates",
    "build_backend",
    "check_parity",
    "create_backend",
    "default_cache_dir",
    "default_threads",
    "open_exported",
    "openvino_supports_bf16",
    "probe_window",
    "probe_windows",
    "select_backend",
    "time_backend",
]
