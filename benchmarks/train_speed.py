"""Training throughput of the steps ``train`` and ``calibrate`` run, variants side by side.

Each variant trains its own fresh model on batches from the real device loader
(:class:`beadsight.train.windows.WindowLoader` over :class:`DeviceWindows`: window
gathering, the rest image's average, label maps, D4, colour jitter) through
:func:`beadsight.train.step.optimizer_step`. Frames are synthetic (a conv net's cost does
not depend on content). Variants run interleaved, ``--rounds`` times ``--steps`` steps
each, each round starting at the next variant, so a machine shared with other work loads
them alike; the table gives each one's
median samples/s (wall clock), CPU seconds per sample, and its ratio to the first variant.

A variant is levers joined by ``+`` (``main`` alone: none of them):

* ``main``: the U-Net as on main before issue 24's speed-ups (``nn.InstanceNorm2d``,
  upsampling before the 1x1 up-conv), foreach AdamW, fp32, torch's default threads;
* ``gn``: the norms as :class:`beadsight.model.InstanceNorm` (group norm, one group per
  channel; the same statistics);
* ``up``: the 1x1 up-conv before the upsampling (:class:`beadsight.model.UpBlock`);
* ``auto``: the thread count chosen as the trainer chooses it
  (:func:`beadsight.train.threads.training_threads`: the faster of torch's default and 1,
  timed again every 2 minutes; its first probe is part of the warm-up, so the table shows
  the steady state);
* ``now``: what ``train`` / ``calibrate`` run now: ``gn``, ``up`` and ``auto``;
* ``t1`` / ``t2`` / ...: ``torch.set_num_threads(N)`` during its steps (instead of ``auto``);
* ``cl``: channels-last memory format (model and input);
* ``fused``: fused AdamW;
* ``compile``: ``torch.compile`` of the U-Net (the compile is in ``warmup_s``);
* ``bf16``: bf16 autocast.

Usage::

    .venv/bin/python benchmarks/train_speed.py                      # 64 px, width 16 and 8
    .venv/bin/python benchmarks/train_speed.py --variants main now t1+now now+cl --json
    .venv/bin/python benchmarks/train_speed.py --size 256 --frames 15 --frame-stride 1 \\
        --no-rest --widths 16 --batch 8 --variants main
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time
import types
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from beadsight.checkpoint import CheckpointMeta, PressureModel
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.data.rest import REST_FRAMES
from beadsight.inference.machine import cpu_summary
from beadsight.model import UpBlock
from beadsight.train.step import optimizer_step
from beadsight.train.threads import PROBE_STEPS, ThreadTuner, training_threads
from beadsight.train.windows import DeviceFrames, DeviceWindows, WindowLabels, WindowLoader

DTYPES = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}
LEVERS = ("main", "now", "gn", "up", "auto", "cl", "fused", "compile", "bf16")
STORE_FRAMES = 2000  # synthetic frames the loader gathers windows from
NOISE_STD = 0.05  # the recipes' input noise


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@dataclass(frozen=True)
class Variant:
    """Levers of one variant (see the module docstring)."""

    name: str
    threads: int | None = None
    gn: bool = False
    up: bool = False
    auto: bool = False
    cl: bool = False
    fused: bool = False
    compile: bool = False
    bf16: bool = False

    @classmethod
    def parse(cls, name: str) -> Variant:
        kw: dict = {}
        for lever in name.split("+"):
            if lever.startswith("t") and lever[1:].isdigit():
                kw["threads"] = int(lever[1:])
            elif lever not in LEVERS:
                raise SystemExit(f"unknown lever {lever!r} in {name!r}; levers: {LEVERS}, tN")
            elif lever == "now":
                kw.update(gn=True, up=True, auto=True)
            elif lever != "main":
                kw[lever] = True
        return cls(name, **kw)


def _main_up(self: UpBlock, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    """UpBlock.forward as on main: upsample, then the conv."""
    up = self.Up(F.interpolate(x, scale_factor=2.0, mode="nearest"))
    return torch.cat([up, skip], dim=1)


def as_on_main(net: torch.nn.Module, variant: Variant) -> None:
    """Undo the U-Net's speed-ups the variant does not have (the weights are unchanged)."""
    for block in net.modules():
        if isinstance(block, UpBlock) and not variant.up:
            block.forward = types.MethodType(_main_up, block)
        if hasattr(block, "layer") and not variant.gn:
            for i in (1, 5):  # ConvBlock's norms
                block.layer[i] = torch.nn.InstanceNorm2d(block.layer[i].num_features)


def make_model(args, device: torch.device, width: int | None = None) -> PressureModel:
    torch.manual_seed(0)
    meta = CheckpointMeta(
        model=ModelConfig(
            frames=args.frames,
            frame_stride=getattr(args, "frame_stride", 1),
            width=width or args.width,
            up_kernel=args.up_kernel,
            dropout=getattr(args, "dropout", 0.2),
            rest_input=getattr(args, "rest", False),
        ),
        geometry=SensorGeometry(image_size_px=args.size),
        pixel_mean=[120.0] * 3,
        pixel_std=[40.0] * 3,
        output_scale_kpa=1.2,
    )
    return PressureModel.create(meta).to(device)


def make_loader(args, device: torch.device) -> WindowLoader:
    """The device loader (the one ``train`` / ``calibrate`` pick when the frames fit in
    memory) over ``STORE_FRAMES`` random frames, each window with a rest image when
    ``args.rest``."""
    span = (args.frames - 1) * args.frame_stride + 1
    g = torch.Generator().manual_seed(0)
    frames = torch.randint(
        0, 256, (STORE_FRAMES, args.size, args.size, 3), generator=g, dtype=torch.uint8
    )
    store = DeviceFrames(frames.to(device), np.arange(STORE_FRAMES))
    rng = np.random.default_rng(0)
    ends = np.arange(max(span, REST_FRAMES) + 1, STORE_FRAMES)
    n = len(ends)
    labels = WindowLabels(
        ends=ends,
        force_n=rng.uniform(0, 20, n),
        position_mm=rng.uniform(-13, 13, (n, 2)),
        contact=rng.uniform(size=n) < 0.8,
        geometry=SensorGeometry(image_size_px=args.size),
        rests=np.full(n, REST_FRAMES - 1) if args.rest else None,
    )
    return WindowLoader(
        DeviceWindows(store, labels, span),
        args.batch,
        device=device,
        shuffle=True,
        augment=args.augment,
        seed=0,
    )


def make_step(args, device: torch.device, precision: str, variant: Variant | None = None):
    """One training step of a fresh model: ``step(frames, targets) -> loss``. Without a
    ``variant``: the U-Net as this checkout builds it."""
    v = variant or Variant("now", gn=True, up=True)
    module = make_model(args, device).module.train()
    as_on_main(module.net, v)
    if v.cl:
        module.to(memory_format=torch.channels_last)
    optimizer = torch.optim.AdamW(
        module.net.parameters(), lr=1e-4, weight_decay=1e-4, fused=v.fused or None
    )
    net = torch.compile(module.net) if v.compile else module.net
    if v.cl:
        inner = net
        net = lambda x: inner(x.contiguous(memory_format=torch.channels_last))  # noqa: E731
    dtype = torch.bfloat16 if v.bf16 else DTYPES[precision]
    scaler = torch.amp.GradScaler("cuda") if dtype == torch.float16 else None

    def step(frames, targets):
        return optimizer_step(
            module,
            net,
            optimizer,
            frames,
            targets,
            output_scale_kpa=1.2,
            noise_std=NOISE_STD,
            color_jitter=getattr(args, "color_jitter", 0.0),
            autocast_dtype=dtype,
            scaler=scaler,
        )

    return step


def samples_per_s(step, warmup: list, timed: list, batch: int, device: torch.device) -> float:
    """Training samples/s of ``step(frames, targets)`` over the ``timed`` (frames, targets)
    batches of ``batch`` samples, after a step on each of the ``warmup`` ones."""
    for frames, targets in warmup:
        step(frames, targets)
    sync(device)
    start = time.perf_counter()
    for frames, targets in timed:
        loss = step(frames, targets)
    loss.item()
    sync(device)
    return len(timed) * batch / (time.perf_counter() - start)


class Runner:
    """One variant at one width: its model, optimizer and loader, stepped in chunks."""

    def __init__(self, args, device: torch.device, variant: Variant, width: int):
        self.args, self.device, self.variant = args, device, variant
        default = torch.get_num_threads()
        if variant.auto and not variant.threads:  # as the trainer chooses
            self.tuner = training_threads(None, device, 1)
        else:
            self.tuner = ThreadTuner([variant.threads or default])
        torch.set_num_threads(default)
        args_w = argparse.Namespace(**{**vars(args), "width": width})
        with self.threaded():
            self.step = make_step(args_w, device, "fp32", variant)
            self.loader = make_loader(args_w, device)
            self.epoch, self.batches = 0, iter(())
            self.threads_used: list[int] = []
            t0 = time.perf_counter()
            # the compile, if any, and the thread tuner's first probe happen here
            self.run(args.warmup + (PROBE_STEPS + 1) * (len(self.tuner.choices) - 1) * 2)
            self.warmup_s = time.perf_counter() - t0
        self.wall: list[float] = []
        self.cpu: list[float] = []

    @contextlib.contextmanager
    def threaded(self) -> Iterator[None]:
        default = torch.get_num_threads()
        torch.set_num_threads(self.tuner.threads)
        try:
            yield
        finally:
            torch.set_num_threads(default)

    def _next(self):
        try:
            return next(self.batches)
        except StopIteration:
            self.epoch += 1
            self.loader.set_epoch(self.epoch)
            self.batches = iter(self.loader)
            return next(self.batches)

    def run(self, steps: int) -> None:
        loss = None
        for _ in range(steps):
            batch = self._next()
            with self.tuner.timed():
                self.threads_used.append(torch.get_num_threads())
                loss = self.step(*batch)
        if loss is not None:
            loss.item()
        sync(self.device)

    def timed(self, steps: int) -> None:
        with self.threaded():
            w0, c0 = time.perf_counter(), time.process_time()
            self.run(steps)
            self.wall.append(time.perf_counter() - w0)
            self.cpu.append(time.process_time() - c0)

    def result(self) -> dict:
        n = self.args.steps * self.args.batch
        return {
            "samples_per_s": n / statistics.median(self.wall),
            "samples_per_s_rounds": [round(n / w, 2) for w in self.wall],
            "cpu_ms_per_sample": 1e3 * statistics.median(self.cpu) / n,
            "threads": sorted(set(self.threads_used[-self.args.steps * self.args.rounds :])),
            "warmup_s": round(self.warmup_s, 2),
        }


def run_variants(args, device: torch.device) -> list[dict]:
    """Every (width, variant): set up (warm-up steps, the compile if any), then
    ``args.rounds`` rounds of ``args.steps`` timed steps each, the variants interleaved."""
    runners = [
        (width, Runner(args, device, Variant.parse(name), width))
        for width in args.widths
        for name in args.variants
    ]
    for r in range(args.rounds):  # each round starts at the next variant: the chunk after
        # another variant's runs slower (measured: up to 1.4x), so no variant is always first
        for _, runner in runners[r % len(runners) :] + runners[: r % len(runners)]:
            runner.timed(args.steps)
    rows = []
    for width, runner in runners:
        first = next(r for w, r in runners if w == width)
        row = {"width": width, "variant": runner.variant.name, **runner.result()}
        row["speedup"] = statistics.median(first.wall) / statistics.median(runner.wall)
        rows.append(row)
    return rows


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--size", type=int, default=64, help="image size in px")
    p.add_argument("--widths", type=int, nargs="+", default=[16, 8], help="U-Net widths")
    p.add_argument("--frames", type=int, default=4, help="T, frames the network sees")
    p.add_argument("--frame-stride", type=int, default=2)
    p.add_argument("--no-rest", dest="rest", action="store_false", help="no rest input")
    p.add_argument("--up-kernel", type=int, default=1)
    p.add_argument("--dropout", type=float, default=0.0)
    p.add_argument(
        "--batch", type=int, default=16, help="training batch (calibrate's default; train: 64)"
    )
    p.add_argument("--augment", action="store_true", help="D4 transforms (train's default)")
    p.add_argument("--color-jitter", type=float, default=0.0)
    p.add_argument("--variants", nargs="+", default=["main", "now"], help="see the docstring")
    p.add_argument("--steps", type=int, default=3, help="timed steps per variant per round")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2, help="untimed steps per variant first")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p.parse_args()


def main() -> None:
    args = parse_args()
    summary = cpu_summary()
    print(summary, file=sys.stderr if args.json else sys.stdout)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    rows = run_variants(args, device)
    result = {
        "cpu": summary,
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "command": " ".join(sys.argv),
        "size": args.size,
        "frames": args.frames,
        "frame_stride": args.frame_stride,
        "rest_input": args.rest,
        "batch": args.batch,
        "augment": args.augment,
        "color_jitter": args.color_jitter,
        "rows": rows,
    }
    if args.json:
        print(json.dumps(result))
        return
    print(
        f"{args.size} px, T={args.frames} stride {args.frame_stride}, rest input {args.rest}, "
        f"batch {args.batch}, device loader; {args.rounds} rounds x {args.steps} steps"
    )
    print(f"{'width':>5} {'variant':<18} {'samples/s':>9} {'x first':>7} {'CPU ms/sample':>13}")
    for r in rows:
        print(
            f"{r['width']:>5} {r['variant']:<18} {r['samples_per_s']:9.2f} {r['speedup']:7.2f} "
            f"{r['cpu_ms_per_sample']:13.1f}"
        )


if __name__ == "__main__":
    main()
