"""Shared pieces of the inference tests (the models are fixtures in conftest.py)."""

from __future__ import annotations

import numpy as np

T = 15  # frames of the probe_model fixture


def stream(n: int, size: int = 64, seed: int = 1) -> np.ndarray:
    """(n, size, size, 3) uint8 random RGB frames."""
    return np.random.default_rng(seed).integers(0, 256, (n, size, size, 3), dtype=np.uint8)
