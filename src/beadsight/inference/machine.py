"""Where inference runs: CPU threads, the cache folder, and a key for this machine.

Quantized models and the auto-selection's timings hold only for the machine and
library versions they were made with; :func:`machine_key` names those.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import importlib.util
import os
import platform
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import torch


def import_openvino() -> ModuleType:
    """The ``openvino`` module (ImportError where it is not installed), with its usage
    telemetry off for this process.

    ``import openvino`` reports to Google Analytics and writes ``~/intel`` unless a consent
    file or a CI variable says no, and nncf reports each quantization. Both send nothing
    when ``openvino_telemetry`` cannot be imported, their own path for a machine without
    it; this arranges that before either loads. Every beadsight import of openvino (and of
    nncf) goes through here."""
    sys.modules.setdefault("openvino_telemetry", None)
    import openvino

    return openvino


class _SignalStack(ctypes.Structure):
    _fields_ = [
        ("ss_sp", ctypes.c_void_p),
        ("ss_flags", ctypes.c_int),
        ("ss_size", ctypes.c_size_t),
    ]


@contextlib.contextmanager
def openvino_signal_stack_kept() -> Iterator[None]:
    """Run OpenVINO work that may load its CPU plugin; afterwards the thread's alternate
    signal stack is the one it had before.

    Each loaded CPU plugin installs its own alternate stack on the loading thread and, when
    unloaded, puts back the one it found there. Two runtimes closed in the order they were
    made (auto selection drops its candidates) left the thread on the first plugin's freed
    stack: the next signal with a Python handler (Ctrl-C, torch's SIGCHLD handler) then
    killed the process with SIGSEGV. Inside this, each plugin finds and later restores the
    thread's own stack. A no-op where libc has no ``sigaltstack``."""
    sigaltstack = getattr(ctypes.CDLL(None), "sigaltstack", None) if os.name == "posix" else None
    if sigaltstack is None:
        yield
        return
    before, now = _SignalStack(), _SignalStack()
    sigaltstack(None, ctypes.byref(before))
    try:
        yield
    finally:
        sigaltstack(None, ctypes.byref(now))
        if bytes(now) != bytes(before):
            sigaltstack(ctypes.byref(before), None)


def default_cache_dir() -> Path:
    """``~/.cache/beadsight``: exported and quantized models, auto decisions."""
    return Path.home() / ".cache" / "beadsight"


def usable_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_threads() -> int:
    """Compute threads of a runtime not told how many: ``OMP_NUM_THREADS`` where set to a
    positive number (torch reads it too, so one variable limits every runtime of a process and
    of its children), at most the usable cores; else all usable cores."""
    cores = usable_cores()
    try:
        limit = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        return cores
    return min(limit, cores) if limit > 0 else cores


def importable(module: str) -> bool:
    """True when ``module`` is installed (without importing it)."""
    return importlib.util.find_spec(module) is not None


def cpu_name() -> str:
    """The CPU's model name, e.g. "Intel(R) Xeon(R) Platinum 8480+"."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


PERFORMANCE_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_tile")


def cpu_flags() -> list[str]:
    """The CPU's vector-instruction flags that decide inference speed (of PERFORMANCE_FLAGS)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                present = set(line.split(":", 1)[1].split())
                return [f for f in PERFORMANCE_FLAGS if f in present]
    except OSError:
        pass
    return []


def cpu_summary() -> str:
    """One line for benchmark output: CPU model, cores this process may use, and flags."""
    flags = " ".join(cpu_flags()) or "none of " + "/".join(PERFORMANCE_FLAGS[:3])
    return f"CPU: {cpu_name()}; {usable_cores()} cores available; flags: {flags}"


def machine_key() -> str:
    """Short hash of what makes timings and compiled code machine-specific."""
    parts = [platform.machine(), cpu_name(), str(default_threads()), torch.__version__]
    try:
        import onnxruntime

        parts.append(f"onnxruntime={onnxruntime.__version__}")
    except ImportError:
        parts.append("onnxruntime=none")
    try:
        ov = import_openvino()
    except ImportError:
        parts.append("openvino=none")
    else:
        with openvino_signal_stack_kept():
            caps = ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
        parts += [f"openvino={ov.__version__}", ",".join(caps)]
    if torch.cuda.is_available():
        parts.append(torch.cuda.get_device_name(0))
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]
