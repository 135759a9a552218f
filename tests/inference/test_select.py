"""Choosing a runtime: "auto" picks the fastest that agrees with torch and caches the choice;
bad requests are refused."""

from __future__ import annotations

import json

import pytest

from beadsight.inference.parity import PARITY_TOLERANCE, check_parity
from beadsight.inference.runtimes import BackendUnavailableError
from beadsight.inference.select import CHOICE_FILE, build_backend, create_backend, select_backend


def test_auto_picks_a_backend_that_passes_parity(probe_model, tmp_path):
    backend = select_backend(probe_model, cache_dir=tmp_path)
    assert backend.parity.ok
    assert check_parity(backend, probe_model).ok
    usable = [c for c in backend.selection if c.seconds is not None]
    assert (backend.name, backend.precision) in [(c.backend, c.precision) for c in usable]
    for c in usable:  # bf16 only within half the bound, fp32 within the bound
        assert c.err_pct <= (100 if c.precision == "fp32" else 50) * PARITY_TOLERANCE.fraction
    fastest = min(usable, key=lambda c: c.seconds)
    assert (fastest.backend, fastest.precision) == (backend.name, backend.precision)
    choices = json.loads((tmp_path / CHOICE_FILE).read_text())
    (choice,) = choices.values()
    assert (choice["backend"], choice["precision"]) == (backend.name, backend.precision)
    cached = select_backend(probe_model, cache_dir=tmp_path)  # from the cached decision
    assert cached.describe() == backend.describe()


def test_auto_with_fp32_only_considers_fp32(probe_model):
    backend = create_backend(probe_model, "auto", "fp32", cache_dir=None)
    assert backend.precision == "fp32"
    assert all(c.precision == "fp32" for c in backend.selection)


def test_bad_backend_arguments(probe_model):
    with pytest.raises(ValueError, match="backend must be"):
        create_backend(probe_model, "tensorrt", cache_dir=None)
    with pytest.raises(ValueError, match="precision must be"):
        create_backend(probe_model, "torch", "fp16", cache_dir=None)
    with pytest.raises(BackendUnavailableError, match="bf16"):
        build_backend(probe_model, "onnx", "bf16", cache_dir=None)
