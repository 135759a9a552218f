"""How many presses a new pouch needs: the calibration curve (issue 14, item 5).

On several simulated pouches the base model never saw (``--variety heldout``), for each
press count N it measures, on the same fixed test presses of that pouch (the last
``--test-presses`` of its file, never trained on):

* ``calibrate``: ``beadsight calibrate --presses N --budget-min B`` (its own split of the
  N presses: ~70 % train, ~10 % early stopping, ~20 % its internal test; the budget
  covers its evaluations too);
* ``scratch``: a model of the base's shape trained from fresh weights on the same N
  presses (same split) for B minutes of training alone (lr 1e-3, cosine), keeping the
  best validation checkpoint;
* ``zero-shot``: the base model as it comes (does not depend on N).

Prints a table (means over pouches; the CPU on top) and writes ``calibration_curve.json``
and ``calibration_curve.png`` into ``--out``.

Usage::

    .venv/bin/python benchmarks/calibration_curve.py                     # 3 pouches, 10 min
    .venv/bin/python benchmarks/calibration_curve.py --pouches 1 --counts 5 10 --budget-min 0.5
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from beadsight.calibrate.config import CALIBRATION_SPLIT, CalibrateConfig
from beadsight.calibrate.run import base_checkpoint, calibrate
from beadsight.checkpoint import load_checkpoint
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.inference.machine import cpu_summary
from beadsight.report.paper import PAPER_METRICS
from beadsight.sim.dataset import simulate_dataset
from beadsight.train.config import TrainConfig
from beadsight.train.trainer import train

METRICS = ("mae_kpa", "force_error_pct", "cop_error_mm", "iou", "worst_region_mae_kpa")
METHODS = ("zero-shot", "calibrate", "scratch")
SCRATCH_LR = 1e-3


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--pouches", type=int, default=3, help="held-out simulated pouches")
    p.add_argument("--counts", type=int, nargs="+", default=[5, 10, 20, 40, 80])
    p.add_argument("--budget-min", type=float, default=10.0, help="minutes per run")
    p.add_argument("--test-presses", type=int, default=10, help="fixed test presses per pouch")
    p.add_argument("--image-size", type=int, default=None, help="default: the base model's")
    p.add_argument("--base", default=None, help="base checkpoint (default: calibrate's)")
    p.add_argument("--seed", type=int, default=100, help="seed of the first pouch")
    p.add_argument("--device", default="auto")
    p.add_argument("--out", type=Path, default=Path("calibration_curve"))
    return p.parse_args()


def scored(model, data: Path, test: np.ndarray, device: str) -> dict:
    settings = EvaluateConfig(device=device, resize=True, plots=False, progress=False)
    m = evaluate(model, data, settings, presses=test)
    return {k: m[k] for k in (*METRICS, "frames", "coverage")}


def scratch(data: Path, out: Path, n: int, base, args) -> Path:
    m = base.meta.model
    config = TrainConfig(
        data=str(data),
        out=str(out),
        presses=n,
        budget_min=args.budget_min,
        epochs=1_000_000,
        frames=m.frames,
        frame_stride=m.frame_stride,
        width=m.width,
        up_kernel=m.up_kernel,
        image_size=base.image_size,
        lr=SCRATCH_LR,
        lr_schedule="cosine",
        lr_min=1e-5,
        batch_size=16,
        split=CALIBRATION_SPLIT,
        val_every_min=0.25,
        device=args.device,
        progress=False,
        checkpoint_every_min=1e6,
    )
    train(config)
    return out / "best.pt"


def one_pouch(p: int, args, base_path: Path, save) -> dict:
    base = load_checkpoint(base_path)
    folder = args.out / f"pouch{p}"
    data = folder / "presses.h5"
    total = max(args.counts) + args.test_presses
    if not data.is_file():
        simulate_dataset(
            data,
            total,
            seed=args.seed + p,
            pouches=1,
            variety="heldout",
            image_size=args.image_size or base.image_size,
            progress=False,
        )
    test = np.arange(total - args.test_presses, total)
    result = {"zero-shot": scored(base, data, test, args.device), "calibrate": {}, "scratch": {}}
    save(result)
    for n in args.counts:
        t0 = time.monotonic()
        cal = CalibrateConfig(
            data=str(data),
            out=str(folder / f"calibrate{n}"),
            base=str(base_path),
            presses=n,
            budget_min=args.budget_min,
            overwrite=True,
            progress=False,
            device=args.device,
        )
        calibrate(cal)
        result["calibrate"][n] = scored(
            folder / f"calibrate{n}" / "model.pt", data, test, args.device
        )
        result["calibrate"][n]["seconds"] = round(time.monotonic() - t0, 1)
        shutil.rmtree(folder / f"scratch{n}", ignore_errors=True)  # a rerun starts afresh
        best = scratch(data, folder / f"scratch{n}", n, base, args)
        result["scratch"][n] = scored(best, data, test, args.device)
        print(
            f"pouch {p}, {n} presses: calibrate {_short(result['calibrate'][n])}; "
            f"scratch {_short(result['scratch'][n])}",
            flush=True,
        )
        save(result)
    return result


def _short(m: dict) -> str:
    return f"force {m['force_error_pct']:.1f} %, MAE {m['mae_kpa']:.3f} kPa, IoU {m['iou']:.2f}"


def mean_over(pouches: list[dict], method: str, n: int | None, key: str) -> float | None:
    values = [(r[method] if n is None else r[method][n]).get(key) for r in pouches]
    values = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(values)) if values else None


def table(pouches: list[dict], counts: list[int]) -> str:
    head = f"{'presses':>7s} {'method':10s} " + " ".join(f"{k:>20s}" for k in METRICS)
    lines = [head, "paper".rjust(18) + " " + " ".join(f"{PAPER_METRICS[k]:20.3f}" for k in METRICS)]
    for n in counts:
        for method in METHODS:
            values = [
                mean_over(pouches, method, None if method == "zero-shot" else n, k) for k in METRICS
            ]
            cells = " ".join(f"{v:20.3f}" if v is not None else f"{'n/a':>20s}" for v in values)
            lines.append(f"{n:7d} {method:10s} {cells}")
    return "\n".join(lines)


def plot(pouches: list[dict], counts: list[int], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.4), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.16, top=0.9, wspace=0.35)
    for ax, key, label in zip(
        axes,
        ("force_error_pct", "mae_kpa", "iou"),
        ("force error (%)", "MAE (kPa)", "contact IoU"),
        strict=True,
    ):
        for method in METHODS:
            ys = [
                mean_over(pouches, method, None if method == "zero-shot" else n, key)
                for n in counts
            ]
            ax.plot(counts, [np.nan if y is None else y for y in ys], "o-", label=method)
        ax.axhline(PAPER_METRICS[key], color="grey", linestyle=":", label="paper")
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks(counts, [str(n) for n in counts])
        ax.set_xlabel("presses of the new pouch")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.savefig(path, format="png")


def main() -> None:
    args = parse()
    args.out.mkdir(parents=True, exist_ok=True)
    print(cpu_summary())
    base_path = base_checkpoint(args.base)
    print(
        f"base {base_path}; {args.pouches} held-out pouches; counts {args.counts}; "
        f"budget {args.budget_min:g} min; {args.test_presses} test presses each",
        flush=True,
    )
    pouches: list[dict] = []

    def save(current: dict) -> None:
        """Write what is measured so far, so an interrupted run keeps its finished points."""
        record = {
            "cpu": cpu_summary(),
            "args": {k: str(v) for k, v in vars(args).items()},
            "base": str(base_path),
            "pouches": [*pouches, current],
        }
        path = args.out / "calibration_curve.json"
        path.with_suffix(".partial").write_text(json.dumps(record, indent=2) + "\n")
        path.with_suffix(".partial").replace(path)

    for p in range(args.pouches):
        pouches.append(one_pouch(p, args, base_path, save))
    print(table(pouches, args.counts))
    plot(pouches, args.counts, args.out / "calibration_curve.png")
    print(f"wrote {args.out / 'calibration_curve.json'} and {args.out / 'calibration_curve.png'}")


if __name__ == "__main__":
    main()
