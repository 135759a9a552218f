"""Offline and live run a rest-referenced model alike: ``predict`` over a dataset gives what
the streaming runtimes give for the same frames and the same rest images."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from beadsight.checkpoint import load_checkpoint
from beadsight.data.dataset import open_dataset
from beadsight.data.windows import RestImages
from beadsight.evaluation.predict import predict_recording
from beadsight.inference.runtimes import CudaGraphBackend, TorchBackend

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # a shared 2-core machine


@pytest.mark.parametrize("ring", ["torch", "device ring on the CPU"])
def test_predict_matches_the_streaming_runtime_with_the_same_rest(rest_run, tmp_path, ring):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    out = predict_recording(model, data, tmp_path / "p.h5", device="cpu", progress=False)
    if ring == "torch":
        backend = TorchBackend(model)
    else:
        backend = CudaGraphBackend(model, "fp32", device="cpu", use_graphs=False)
    with open_dataset(data) as ds, h5py.File(out, "r") as f:
        valid, maps = f["valid"][()], f["pressure_kpa"][()]
        rests = RestImages(ds)
        frames = ds.read_frames(0, len(ds))
        span, streamed = model.span, []
        for end in np.flatnonzero(valid).tolist():  # one new frame per call, as live
            window = frames[None, end - span + 1 : end + 1]
            streamed.append(backend.run_incremental(window, 1, rests([end])[0])[0])
        assert rests.ends[np.flatnonzero(valid)].min() >= 0 and len(set(rests.ends[valid])) > 1
    np.testing.assert_allclose(maps[valid], np.stack(streamed), rtol=1e-4, atol=1e-4)
