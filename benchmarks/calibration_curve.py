"""How many presses a new pouch needs: the calibration curve (issue 14, item 5), on the
simulator's own look or on its look families (``benchmarks/foreign_look.py`` runs it on the
held-out ones, issue 24 item 7).

For each look (``--families``: ``own``, the simulator's own look, and/or families of
:mod:`beadsight.sim.looks`) and each of ``--pouches`` simulated pouches the base model never
saw (``--variety heldout`` builds, seeds ``--seed``, ``--seed`` + 1, ...; a family's look is
drawn on top of the build), for each press count N of ``--counts`` it measures, on the same
fixed test presses of that pouch (the last ``--test-presses`` of its file, never trained on
and never used to choose):

* ``calibrate``: ``beadsight calibrate --presses N --budget-min B`` (its own split of the
  N presses: ~70 % train, ~20 % early stopping, ~10 % its internal test; the budget covers
  its evaluations too). N = 0 is ``calibrate --presses 0`` (rest frames only: the
  pre-contact frames of the pouch's presses); its model does not depend on the budget
  (which sets only how many frames calibrate scores it on itself), so it runs with
  :data:`ZERO_PRESS_BUDGET_MIN`. The fine-tunings it scored and did not keep are scored on
  the fixed presses too (``not_kept`` in the record: what its choice cost);
* ``scratch`` (N > 0): calibrate's own ``scratch`` candidate (a width-8 model, lr 1e-3
  cosine, no dropout, batch 16, the base model's frames, stride, rest input and image size:
  the command of issue 24) trained with ``beadsight train`` on the same N presses with the
  same split, for B minutes of training alone (its setup and its scoring not counted: the
  benefit of the doubt goes to scratch), keeping its best early-stopping checkpoint;
* ``zero-shot``: the base model as it comes (does not depend on N).

Every point is written to ``OUT/NAME.json`` atomically as soon as it is measured, so an
interrupted multi-hour run keeps what it finished; rerunning with the same ``--out`` skips
the points already there (a file measured with other settings is refused). Prints the CPU,
then one table per look (means over pouches, each calibrate run's kept candidate, Markdown
for docs/calibration.md), writes ``OUT/NAME.png`` and prints a JSON object last.

Usage::

    .venv/bin/python benchmarks/calibration_curve.py                     # 3 pouches, 10 min
    .venv/bin/python benchmarks/calibration_curve.py --pouches 1 --counts 5 10 --budget-min 0.5
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from beadsight.calibrate.candidates import candidate_config
from beadsight.calibrate.config import FINE_TUNED, MIN_PRESSES, TRAIN_FOLDER, CalibrateConfig
from beadsight.calibrate.run import base_checkpoint, calibrate, check_data
from beadsight.calibrate.tuning import VAL_MAX_FRAMES, with_val_stride
from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.data.dataset import open_dataset
from beadsight.errors import BeadSightError, ConfigError
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.files import atomic_write_json, read_json_object
from beadsight.inference.machine import cpu_summary
from beadsight.metrics import PAPER_METRIC_KEYS
from beadsight.report.paper import PAPER_METRICS
from beadsight.sim.looks import FAMILY_NAMES
from beadsight.train.run import BEST_CHECKPOINT
from beadsight.train.trainer import train

METRICS = PAPER_METRIC_KEYS  # MAE kPa, force error %, CoP mm, IoU, worst region kPa
FIGURES = (*METRICS, "frames", "coverage")
OWN_LOOK = "own"  # --families: the simulator's own look (no look family drawn)
VARIETY = "heldout"  # the pouches' builds: a split the base model never saw
ZERO_PRESS_BUDGET_MIN = 0.5  # calibrate --presses 0: its model does not depend on the budget
# The settings a measured point depends on: a rerun with other values is refused.
SETTINGS = ("base", "budget_min", "test_presses", "test_frames", "image_size", "variety")


def parser(
    description: str,
    *,
    families: list[str],
    counts: list[int],
    pouches: int,
    out: str,
) -> argparse.ArgumentParser:
    """The command line of the curve, with these defaults (foreign_look.py sets its own)."""
    p = argparse.ArgumentParser(
        description=description, formatter_class=argparse.RawTextHelpFormatter
    )
    p.add_argument(
        "--families",
        nargs="+",
        default=families,
        choices=(OWN_LOOK, *FAMILY_NAMES),
        help=f"looks of the pouches ('{OWN_LOOK}': the simulator's own; default: "
        f"{' '.join(families)})",
    )
    p.add_argument("--pouches", type=int, default=pouches, help="pouches per look")
    p.add_argument(
        "--counts",
        type=int,
        nargs="+",
        default=counts,
        help=f"press counts (0: calibrate --presses 0, rest frames only; else >= {MIN_PRESSES})",
    )
    p.add_argument("--budget-min", type=float, default=10.0, help="minutes per run")
    p.add_argument("--test-presses", type=int, default=10, help="fixed test presses per pouch")
    p.add_argument(
        "--test-frames",
        type=int,
        default=None,
        help="score at most this many test frames, spread evenly (default: all; fewer "
        "for a quick check, and the coverage says so)",
    )
    p.add_argument("--image-size", type=int, default=None, help="default: the base model's")
    p.add_argument("--base", default=None, help="base checkpoint (default: calibrate's)")
    p.add_argument("--seed", type=int, default=100, help="seed of each look's first pouch")
    p.add_argument("--device", default="auto")
    p.add_argument("--out", type=Path, default=Path(out), help="output folder; rerun to resume")
    return p


def checked(p: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse ``argv`` and check the values (argparse's error names the flag)."""
    args = p.parse_args(argv)
    if args.pouches < 1 or args.test_presses < 1:
        p.error(f"--pouches and --test-presses must be >= 1 ({args.pouches}, {args.test_presses})")
    if any(n < 0 or 0 < n < MIN_PRESSES for n in args.counts):
        p.error(f"--counts must be 0 or >= {MIN_PRESSES} (calibrate's minimum), got {args.counts}")
    if not 0 < args.budget_min < math.inf:
        p.error(f"--budget-min must be finite and > 0, got {args.budget_min}")
    if args.test_frames is not None and args.test_frames < 1:
        p.error(f"--test-frames must be >= 1, got {args.test_frames}")
    args.counts = sorted(set(args.counts))
    args.families = list(dict.fromkeys(args.families))
    return args


class Record:
    """``OUT/NAME.json``: the settings, the CPUs it ran on, and every pouch's points
    (``{"family", "seed", "presses", "data", "zero-shot", "calibrate": {"N": ...},
    "scratch": {"N": ...}}``), written atomically after every point."""

    def __init__(self, path: Path, settings: dict):
        self.path = path
        if path.is_file():
            self.data = read_json_object(path, ConfigError, "a benchmark record")
            if not isinstance(self.data.get("settings"), dict) or not isinstance(
                self.data.get("pouches"), list
            ):
                raise ConfigError(f"{path}: not a record of this benchmark (settings, pouches)")
            for key in SETTINGS:
                if self.data["settings"].get(key) != settings[key]:
                    raise ConfigError(
                        f"{path}: measured with {key} {self.data['settings'].get(key)!r}, this "
                        f"run asks {settings[key]!r}; use another --out, or the same settings "
                        "to resume"
                    )
        else:
            self.data = {"settings": settings, "cpu": [], "pouches": []}
        cpus = self.data.setdefault("cpu", [])  # every CPU that ran it
        if cpu_summary() not in cpus:
            cpus.append(cpu_summary())

    def pouch(self, family: str, seed: int, presses: int, data: str) -> dict:
        """The entry of pouch (``family``, ``seed``), made if new."""
        for entry in self.data["pouches"]:
            if entry["family"] == family and entry["seed"] == seed:
                return entry
        entry = {"family": family, "seed": seed, "presses": presses, "data": data}
        entry.update({"zero-shot": None, "calibrate": {}, "scratch": {}})
        self.data["pouches"].append(entry)
        self.save()
        return entry

    def pouches(self, family: str, seeds: list[int]) -> list[dict]:
        return [
            p
            for s in seeds
            for p in self.data["pouches"]
            if (p["family"], p["seed"]) == (family, s)
        ]

    def save(self) -> None:
        atomic_write_json(self.path, self.data)


def scored(model, data: Path, test: np.ndarray, args) -> dict:
    """The figures of ``model`` on the fixed ``test`` presses of ``data``."""
    settings = EvaluateConfig(
        device=args.device,
        max_frames=args.test_frames,
        resize=True,
        plots=False,
        progress=False,
    )
    m = evaluate(model, data, settings, presses=test)
    return {k: m[k] for k in FIGURES}


def calibrated(data: Path, folder: Path, n: int, base_path: Path, test: np.ndarray, args) -> dict:
    """``calibrate --presses n`` into ``folder``, scored on ``test``; with the candidate it
    kept, whether any fine-tuning step was taken, and its own wall time."""
    budget = args.budget_min if n else min(args.budget_min, ZERO_PRESS_BUDGET_MIN)
    t0 = time.monotonic()
    m = calibrate(
        CalibrateConfig(
            data=str(data),
            out=str(folder),
            base=str(base_path),
            presses=n,
            budget_min=budget,
            overwrite=True,
            progress=False,
            device=args.device,
        ),
        started=t0,
    )
    seconds = time.monotonic() - t0
    chosen = m["chosen"]
    # the fine-tunings it did not keep, on the same fixed presses: what the choice cost
    not_kept = {
        name: scored(folder / TRAIN_FOLDER / name / BEST_CHECKPOINT, data, test, args)
        for name, c in m["candidates"].items()
        if name in FINE_TUNED and name != chosen and c["status"] == "scored"
    }
    return {
        **scored(folder / "model.pt", data, test, args),
        "chosen": chosen,
        "steps": m["candidates"][chosen]["steps"],
        "fine_tuned": m["calibration"]["fine_tuned"],
        "budget_min": budget,
        "seconds": round(seconds, 1),
        "not_kept": not_kept,
    }


def from_scratch(
    data: Path, folder: Path, n: int, base: PressureModel, base_path: Path, test, args
) -> dict:
    """calibrate's scratch candidate, trained alone on calibrate's split of the first ``n``
    presses for ``--budget-min`` minutes of training (it validates on at most
    ``VAL_MAX_FRAMES`` early-stopping frames, as calibrate's would), scored on ``test``."""
    cal = CalibrateConfig(
        data=str(data),
        out=str(folder),
        base=str(base_path),
        presses=n,
        budget_min=args.budget_min,
        progress=False,
        device=args.device,
    )
    config = candidate_config("scratch", cal, base, base_path, folder)
    config = with_val_stride(config, check_data(cal, base)["windows"]["val"], VAL_MAX_FRAMES)
    config = dataclasses.replace(config, out=str(folder), budget_min=args.budget_min)
    shutil.rmtree(folder, ignore_errors=True)  # a rerun starts afresh
    t0 = time.monotonic()
    train(config)
    seconds = time.monotonic() - t0
    return {**scored(folder / "best.pt", data, test, args), "seconds": round(seconds, 1)}


def pouch_data(folder: Path, family: str, seed: int, total: int, image_size: int) -> Path:
    """The pouch's presses (``folder/presses.h5``), simulated unless a finished file is there."""
    data = folder / "presses.h5"
    if data.is_file():
        with open_dataset(data) as ds:
            if ds.num_presses != total:
                raise ConfigError(
                    f"{data}: {ds.num_presses} presses, this pouch has {total}; remove the "
                    "file or use another --out"
                )
        return data
    from beadsight.sim.dataset import simulate_dataset

    folder.mkdir(parents=True, exist_ok=True)
    return simulate_dataset(
        data,
        total,
        seed=seed,
        pouches=1,
        variety=VARIETY,
        looks=None if family == OWN_LOOK else family,
        image_size=image_size,
        overwrite=True,
        progress=False,
    )


def one_pouch(record: Record, family: str, seed: int, args, base_path: Path) -> None:
    """Measure the points of pouch (``family``, ``seed``) that ``record`` lacks."""
    base = load_checkpoint(base_path)
    folder = args.out / family / f"pouch{seed}"
    total = max(args.counts) + args.test_presses
    entry = record.pouch(family, seed, total, str(folder.relative_to(args.out) / "presses.h5"))
    if max(args.counts) > entry["presses"] - args.test_presses:
        raise ConfigError(
            f"{record.path}: pouch {family} {seed} has {entry['presses']} presses, the last "
            f"{args.test_presses} for the test; {max(args.counts)} presses to calibrate on "
            "would reach them: use another --out for larger counts"
        )
    data = pouch_data(folder, family, seed, entry["presses"], args.image_size or base.image_size)
    test = np.arange(entry["presses"] - args.test_presses, entry["presses"])
    if entry["zero-shot"] is None:
        entry["zero-shot"] = scored(base, data, test, args)
        record.save()
    for n in args.counts:
        key = str(n)
        if key not in entry["calibrate"]:
            entry["calibrate"][key] = calibrated(
                data, folder / f"calibrate{n}", n, base_path, test, args
            )
            record.save()
        if n and key not in entry["scratch"]:
            entry["scratch"][key] = from_scratch(
                data, folder / f"scratch{n}", n, base, base_path, test, args
            )
            record.save()
        print(f"{family} pouch {seed}, {n} presses: {_short(entry, key)}", flush=True)


def _short(entry: dict, key: str) -> str:
    def one(m: dict | None) -> str:
        if m is None:
            return "-"
        return f"force {m['force_error_pct']:.1f} %, MAE {m['mae_kpa']:.3f} kPa, IoU {m['iou']:.2f}"

    cal = entry["calibrate"][key]
    return f"calibrate {one(cal)} (kept {cal['chosen']}); scratch {one(entry['scratch'].get(key))}"


def rows(pouches: list[dict], counts: list[int]) -> list[tuple[str, str, list[dict]]]:
    """(presses, run, the pouches' points) of a look's table, zero-shot first."""
    out = [("–", "zero-shot", [p["zero-shot"] for p in pouches if p["zero-shot"]])]
    for n in counts:
        for method in ("calibrate", "scratch") if n else ("calibrate",):
            points = [p[method][str(n)] for p in pouches if str(n) in p[method]]
            out.append((str(n), "calibrate --presses 0" if not n else method, points))
    return out


def mean(points: list[dict], key: str) -> float | None:
    values = [p.get(key) for p in points]
    values = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(values)) if values else None


def table(pouches: list[dict], counts: list[int]) -> str:
    """A Markdown table of one look: means over its pouches, each run's kept candidate."""
    fmt = {"mae_kpa": "{:.3f}", "force_error_pct": "{:.1f}", "cop_error_mm": "{:.2f}"}
    fmt |= {"iou": "{:.3f}", "worst_region_mae_kpa": "{:.3f}"}
    lines = [
        "| presses | run | pouches | MAE kPa | force % | CoP mm | IoU | worst kPa | coverage % "
        "| kept (per pouch) | s (mean) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for n, method, points in rows(pouches, counts):
        cells = [fmt[k].format(v) if (v := mean(points, k)) is not None else "n/a" for k in METRICS]
        cov = mean(points, "coverage")
        kept = ", ".join(p["chosen"] for p in points if "chosen" in p)
        secs = mean(points, "seconds")
        lines.append(
            f"| {n} | {method} | {len(points)} | {' | '.join(cells)} | "
            f"{'n/a' if cov is None else f'{100 * cov:.0f}'} | {kept} | "
            f"{'' if secs is None else f'{secs:.0f}'} |"
        )
    paper = " | ".join(fmt[k].format(PAPER_METRICS[k]) for k in METRICS)
    lines.append(f"| | paper | | {paper} | | | |")
    return "\n".join(lines)


def plot(
    record: Record, families: list[str], seeds: list[int], counts: list[int], path: Path
) -> None:
    """Force error, MAE and IoU against the press count, one row per look."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 0.4 + 3.0 * len(families)), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(families), 3, squeeze=False)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.93, wspace=0.35, hspace=0.45)
    x = np.arange(len(counts))  # press counts as categories: 0 has no place on a log axis
    panels = (
        ("force_error_pct", "force error (%)"),
        ("mae_kpa", "MAE (kPa)"),
        ("iou", "contact IoU"),
    )
    for row, family in zip(axes, families, strict=True):
        pouches = record.pouches(family, seeds)
        for ax, (key, label) in zip(row, panels, strict=True):
            zero = mean([p["zero-shot"] for p in pouches if p["zero-shot"]], key)
            if zero is not None:
                ax.axhline(zero, color="C0", linestyle="--", label="zero-shot")
            for colour, method in (("C1", "calibrate"), ("C2", "scratch")):
                ys = [
                    mean([p[method][str(n)] for p in pouches if str(n) in p[method]], key)
                    for n in counts
                ]
                ax.plot(
                    x, [np.nan if y is None else y for y in ys], "o-", color=colour, label=method
                )
            ax.axhline(PAPER_METRICS[key], color="grey", linestyle=":", label="paper")
            ax.set_xticks(x, [str(n) for n in counts])
            ax.set_xlabel("presses of the new pouch")
            ax.set_ylabel(label)
            ax.set_title(f"{family} ({len(pouches)} pouches)", fontsize=8)
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.savefig(path, format="png")


def run(args: argparse.Namespace, name: str, after: Callable[[Record], dict] | None = None) -> dict:
    """Measure what ``args`` asks (resuming ``OUT/NAME.json``), print the tables, write the
    plot; ``after(record)`` adds a summary (foreign_look.py's targets). Prints and returns
    the JSON summary."""
    args.out.mkdir(parents=True, exist_ok=True)
    print(cpu_summary())
    base_path = base_checkpoint(args.base).resolve()
    settings = {
        "base": str(base_path),
        "budget_min": args.budget_min,
        "test_presses": args.test_presses,
        "test_frames": args.test_frames,
        "image_size": args.image_size,
        "variety": VARIETY,
        "scratch": "calibrate's scratch candidate, trained alone for budget_min of training",
        "zero_press_budget_min": ZERO_PRESS_BUDGET_MIN,
    }
    record = Record(args.out / f"{name}.json", settings)
    seeds = [args.seed + p for p in range(args.pouches)]
    print(
        f"base {base_path}; looks {' '.join(args.families)}; {args.pouches} pouches each "
        f"(seeds {seeds[0]}-{seeds[-1]}); counts {args.counts}; budget {args.budget_min:g} min; "
        f"{args.test_presses} test presses each; {record.path}",
        flush=True,
    )
    for family in args.families:
        for seed in seeds:
            one_pouch(record, family, seed, args, base_path)
    for family in args.families:
        print(f"\n{family} (seeds {seeds[0]}-{seeds[-1]}):\n")
        print(table(record.pouches(family, seeds), args.counts))
    plot(record, args.families, seeds, args.counts, args.out / f"{name}.png")
    summary = {
        "json": str(record.path),
        "plot": str(args.out / f"{name}.png"),
        "cpu": cpu_summary(),
    }
    if after is not None:
        summary.update(after(record))
        record.data["summary"] = summary
        record.save()
    print(json.dumps(summary))
    return summary


def main(argv: list[str] | None = None) -> dict:
    p = parser(
        __doc__, families=[OWN_LOOK], counts=[5, 10, 20, 40, 80], pouches=3, out="calibration_curve"
    )
    return run(checked(p, argv), "calibration_curve")


if __name__ == "__main__":
    try:
        main()
    except BeadSightError as e:
        sys.exit(f"error: {e}")
