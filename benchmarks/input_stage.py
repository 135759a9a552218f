"""The input stage of the network on OpenVINO, measured piece by piece (issue 25, item 2).

Target: find what a fused input stage can win at the reference size (256 px, width 16,
15 frames, random weights). Each variant is exported to ONNX, compiled by OpenVINO
(fp32, all usable cores, latency hint) and timed in the same run, interleaved, so only
the ratios between them mean something on a shared machine:

* ``graph``: today's exported model: uint8 NHWC window in, cast, ``(x - mean) / std``
  and the NHWC -> NCHW transpose inside the graph, then the U-Net;
* ``folded``: uint8 NHWC in, ``x - mean`` in the graph, the ``1 / std`` folded into the
  first convolution's weights (exactly equivalent: zero padding of ``x - mean`` scaled
  is zero padding of the normalised input);
* ``network``: the U-Net alone on an already normalised float NCHW input: the floor
  any fused input stage can reach (the input stage's whole cost is graph - network);

and, in numpy, the per-frame cost of building a rest model's input by copying the
window behind the rest image (``Backend.run_incremental``'s ``np.concatenate``) against
using the predictor's ring view as it is.

    .venv/bin/python benchmarks/input_stage.py [--runs 40] [--json]
"""

from __future__ import annotations

import argparse
import io
import json
import time
import warnings

import numpy as np
import torch

from beadsight.inference.machine import cpu_summary, default_threads
from beadsight.live.bench import random_model


class Folded(torch.nn.Module):
    """uint8 NHWC -> ``x - mean`` in the graph; 1/std folded into the first conv."""

    def __init__(self, module):
        super().__init__()
        self.module = module
        net = module.net
        conv = net.C1.layer[0]
        std = module.pixel_std[module.channel_perm]
        # input channel k = 3 t + c: divide its weights by std[c]
        scale = (1.0 / std).repeat(conv.weight.shape[1] // 3)
        with torch.no_grad():
            conv.weight.mul_(scale[None, :, None, None])

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        m = self.module
        x = frames.index_select(-1, m.channel_perm).to(torch.float32) - m.pixel_mean
        x = m.seen(x.permute(0, 1, 4, 2, 3)).flatten(1, 2)  # (B, 3T, H, W), not scaled
        return m.pressure(x)


class Network(torch.nn.Module):
    def __init__(self, module):
        super().__init__()
        self.module = module

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.module.pressure(x)


def _compile(module: torch.nn.Module, example: torch.Tensor, threads: int):
    import openvino as ov

    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, (example,), buffer, dynamo=False, opset_version=17)
    core = ov.Core()
    model = core.read_model(buffer.getvalue())
    config = {
        "INFERENCE_PRECISION_HINT": "f32",
        "INFERENCE_NUM_THREADS": threads,
        "PERFORMANCE_HINT": "LATENCY",
        "NUM_STREAMS": 1,
    }
    return core.compile_model(model, "CPU", config).create_infer_request()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=40, help="timed runs per variant")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    threads = default_threads()
    torch.set_num_threads(threads)
    model = random_model()
    s, n = model.image_size, model.inputs
    rng = np.random.default_rng(0)
    window = rng.integers(0, 256, size=(1, n, s, s, 3), dtype=np.uint8)
    normalised = model.module.normalize(torch.from_numpy(window)).numpy()
    reference = model.predict(window, batch_size=1)
    variants = {
        "graph": (_compile(model.module, torch.from_numpy(window), threads), window),
        "network": (
            _compile(Network(model.module), torch.from_numpy(normalised), threads),
            normalised,
        ),
    }
    folded_model = random_model()  # a copy whose first conv is rescaled
    variants["folded"] = (
        _compile(Folded(folded_model.module), torch.from_numpy(window), threads),
        window,
    )
    errors = {}
    for name, (request, x) in variants.items():
        got = request.infer({0: x})[0]
        errors[name] = float(np.abs(got - reference).max() / max(np.abs(reference).max(), 1e-9))
    times = {name: [] for name in variants}
    for _ in range(3):  # warm-up
        for request, x in variants.values():
            request.infer({0: x}, share_inputs=True)
    for _ in range(args.runs):  # interleaved: load changes hit every variant alike
        for name, (request, x) in variants.items():
            t = time.perf_counter()
            request.infer({0: x}, share_inputs=True)
            times[name].append(time.perf_counter() - t)
    rest = window[0, 0]
    ring = np.zeros((1, 2 * (n - 1), s, s, 3), np.uint8)
    copy_s, view_s = [], []
    for k in range(200):
        view = ring[:, k % (n - 1) : k % (n - 1) + n - 1]
        t = time.perf_counter()
        np.concatenate([rest[None, None], view], axis=1)
        copy_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        np.ascontiguousarray(view)
        view_s.append(time.perf_counter() - t)
    p50 = {k: float(np.median(v) * 1e3) for k, v in times.items()}
    result = {
        "cpu": cpu_summary(),
        "model": "reference size: 256 px, width 16, 15 frames (random weights)",
        "runs": args.runs,
        "p50_ms": p50,
        "input_stage_ms": p50["graph"] - p50["network"],
        "input_stage_share": (p50["graph"] - p50["network"]) / p50["graph"],
        "folded_vs_graph": p50["folded"] / p50["graph"],
        "max_rel_err_vs_torch": errors,
        "window_copy_ms_p50": float(np.median(copy_s) * 1e3),
        "ring_view_ms_p50": float(np.median(view_s) * 1e3),
    }
    if not args.json:
        print(result["cpu"])
        for name, ms in p50.items():
            print(f"  {name:8s} p50 {ms:7.2f} ms   max error {100 * errors[name]:.2g} % of peak")
        print(
            f"  input stage {result['input_stage_ms']:.2f} ms "
            f"({100 * result['input_stage_share']:.1f} %), folded/graph "
            f"{result['folded_vs_graph']:.3f}, rest+window copy "
            f"{result['window_copy_ms_p50']:.2f} ms per frame"
        )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
