"""Shared by the training tests: import `one_torch_thread` (an autouse fixture) into a test module."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def one_torch_thread():
    """The test machine is shared: one intra-op thread avoids spin-wait thrashing."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
