"""The input stage of the file runtimes, streaming, before and after the plane ring (issue 25, item 2).

The runtimes built from a checkpoint run the network alone on float32 planes that each
frame gets once (:mod:`beadsight.inference.planes`). Before, they ran the whole exported
module on every call: the uint8 window (with the rest image put in front of it: a copy)
cast, normalised, transposed and differenced inside the graph. This benchmark streams
the same frames, one new frame per call and a fixed rest image, through both, calls
interleaved so that load changes hit both alike (only the ratios mean something on a
shared machine):

* ``module graph``: the whole module exported to ONNX (what ``beadsight export``
  writes), fp32, or quantized by the same int8 recipe on the same calibration windows;
* ``plane ring``: the ``openvino`` / ``int8`` runtime as ``live`` runs it.

It also times the ring's work per frame against the module's own torch steps for it.

    .venv/bin/python benchmarks/input_stage.py [--checkpoint benchmarks/models/reference_size.pt]
        [--frames 200] [--tiers "openvino fp32" int8] [--json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from beadsight.checkpoint import load_checkpoint
from beadsight.errors import BeadSightError
from beadsight.inference.export_format import write_onnx
from beadsight.inference.int8 import FAST, Int8Backend, calibration_windows, quantize
from beadsight.inference.machine import cpu_summary, default_threads
from beadsight.inference.planes import PlaneRing
from beadsight.inference.runtimes import OpenVinoBackend

REFERENCE = Path(__file__).parent / "models" / "reference_size.pt"


def _module_graph(model, threads: int, tmp: Path, int8: bool) -> OpenVinoBackend:
    """The OpenVINO runtime on the whole exported module (as it runs a file made by
    ``beadsight export``: the rest image copied in front of the window per call), fp32 or
    quantized by ``FAST`` on the same calibration windows as the int8 runtime."""
    path = write_onnx(model, tmp / "module.onnx")
    if int8:
        shape = (1, model.inputs, model.image_size, model.image_size, 3)
        path = quantize(path, shape, calibration_windows(model), tmp / "module_int8.xml", FAST)
    return OpenVinoBackend(model, "fp32", exported_model=path, threads=threads)


def _ms(seconds: list[float]) -> dict[str, float]:
    a = np.asarray(seconds[20:]) * 1e3
    return {"p50": round(float(np.median(a)), 2), "p99": round(float(np.percentile(a, 99)), 2)}


TIERS = {"openvino fp32": False, "int8": True}  # tier -> quantized


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", default=str(REFERENCE))
    parser.add_argument("--frames", type=int, default=200, help="streamed frames per variant")
    parser.add_argument("--tiers", nargs="+", choices=list(TIERS), default=list(TIERS))
    parser.add_argument("--json", action="store_true", help="only the JSON line")
    args = parser.parse_args(argv)
    if args.frames < 1:
        parser.error(f"--frames must be >= 1, got {args.frames}")
    threads = default_threads()
    try:
        model = load_checkpoint(args.checkpoint)
    except BeadSightError as error:  # a missing or foreign checkpoint
        parser.error(str(error))
    rng = np.random.default_rng(0)
    s, span = model.image_size, model.span
    frames = rng.integers(0, 256, size=(span + args.frames + 20, s, s, 3), dtype=np.uint8)
    rest = rng.integers(0, 256, size=(s, s, 3), dtype=np.uint8) if model.rest else None
    result: dict = {"cpu": cpu_summary(), "checkpoint": args.checkpoint, "threads": threads}
    with tempfile.TemporaryDirectory() as tmp:
        for tier in args.tiers:
            int8 = TIERS[tier]
            before = _module_graph(model, threads, Path(tmp), int8)
            if int8:
                after = Int8Backend(model, threads=threads, recipe=FAST)
            else:
                after = OpenVinoBackend(model, "fp32", threads=threads)
            times: dict[str, list[float]] = {"module graph": [], "plane ring": []}
            diff = 0.0  # the two outputs' largest difference (int8: two quantizations)
            for end in range(span - 1, len(frames)):
                window = frames[None, end - span + 1 : end + 1]
                new = span if end == span - 1 else 1
                t0 = time.perf_counter()
                a = before.run_incremental(window, new, rest)
                t1 = time.perf_counter()
                b = after.run_incremental(window, new, rest)
                t2 = time.perf_counter()
                diff = max(diff, float(np.abs(a - b).max()))
                times["module graph"].append(t1 - t0)
                times["plane ring"].append(t2 - t1)
            row = {name: _ms(v) for name, v in times.items()}
            row["speedup_p50"] = round(row["module graph"]["p50"] / row["plane ring"]["p50"], 3)
            row["max_abs_diff_kpa"] = diff
            result[tier] = row
            before.close()
            after.close()
    ring = PlaneRing(model.module, model.image_size)
    window = frames[None, :span]
    ring.update(window, span, rest)
    per_frame: dict[str, list[float]] = {"ring (numpy)": [], "module steps (torch)": []}
    module = model.module
    with torch.inference_mode():
        rest_x = (
            None if rest is None else module.normalize_frames(torch.from_numpy(rest)[None, None])
        )
    for k in range(min(120, len(frames) - span)):
        t0 = time.perf_counter()
        ring.update(frames[None, k + 1 : k + 1 + span], 1, rest)
        t1 = time.perf_counter()
        with torch.inference_mode():  # what the ring does, by the module's steps
            x = module.normalize_frames(torch.from_numpy(frames[k + span])[None, None])
            if rest_x is not None:
                x = module.rest_terms(rest_x, x)[1]
            x.numpy().copy()
        t2 = time.perf_counter()
        per_frame["ring (numpy)"].append(t1 - t0)
        per_frame["module steps (torch)"].append(t2 - t1)
    result["per_frame_ms"] = {name: _ms(v)["p50"] for name, v in per_frame.items()}
    if not args.json:
        print(result["cpu"])
        for tier in args.tiers:
            r = result[tier]
            print(
                f"  {tier:13s} module graph p50 {r['module graph']['p50']:6.2f} p99 "
                f"{r['module graph']['p99']:6.2f} ms | plane ring p50 {r['plane ring']['p50']:6.2f}"
                f" p99 {r['plane ring']['p99']:6.2f} ms | {r['speedup_p50']:.3f}x | outputs "
                f"differ by <= {r['max_abs_diff_kpa']:.2g} kPa"
            )
        print(f"  per frame: {result['per_frame_ms']}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
