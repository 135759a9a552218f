"""Offline and live run a rest-referenced model alike: ``predict`` over a dataset gives what
the streaming runtimes give for the same frames and the same rest images."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from beadsight.checkpoint import load_checkpoint
from beadsight.data.dataset import open_dataset
from beadsight.data.windows import RestImages
from beadsight.evaluation.predict import predict_recording
from beadsight.inference.runtimes import CudaGraphBackend, OpenVinoBackend, TorchBackend

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # a shared 2-core machine


@pytest.fixture(scope="module")
def offline(rest_run, tmp_path_factory) -> tuple[np.ndarray, np.ndarray]:
    """``predict``'s (valid, pressure_kpa) over the rest run's dataset: both streaming
    runtimes are held to the same file, so it is written once."""
    data, checkpoint = rest_run
    out = tmp_path_factory.mktemp("offline") / "p.h5"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as one_torch_thread, which a module fixture cannot use
    try:
        predict_recording(load_checkpoint(checkpoint), data, out, device="cpu", progress=False)
    finally:
        torch.set_num_threads(threads)
    with h5py.File(out, "r") as f:
        return f["valid"][()], f["pressure_kpa"][()]


@pytest.mark.parametrize("ring", ["torch", "device ring on the CPU", "openvino planes"])
def test_predict_matches_the_streaming_runtime_with_the_same_rest(rest_run, offline, ring):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    valid, maps = offline
    if ring == "torch":
        backend = TorchBackend(model)
    elif ring == "openvino planes":  # a new rest image recomputes the ring's planes
        backend = OpenVinoBackend(model, "fp32", threads=1)
    else:
        backend = CudaGraphBackend(model, "fp32", device="cpu", use_graphs=False)
    with open_dataset(data) as ds:
        rests = RestImages(ds)
        frames = ds.read_frames(0, len(ds))
        span, streamed = model.span, []
        for end in np.flatnonzero(valid).tolist():  # one new frame per call, as live
            window = frames[None, end - span + 1 : end + 1]
            streamed.append(backend.run_incremental(window, 1, rests([end])[0])[0])
        assert rests.ends[np.flatnonzero(valid)].min() >= 0 and len(set(rests.ends[valid])) > 1
    np.testing.assert_allclose(maps[valid], np.stack(streamed), rtol=1e-4, atol=1e-4)
