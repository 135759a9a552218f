"""Where a model's total-force error comes from: per-press gain and dropout's scale shift.

``press-gain``: from a ``beadsight evaluate`` folder's predictions.h5, the ratio
of predicted to true total force of each press (over its contact frames), its
mean and standard deviation, and the force error left once each press is divided
by its own ratio (what a model that reads every press's stiffness right would
score).

``spatial-gain``: whether a gain map over the pad, fitted on a pouch's first presses,
predicts the later presses' gains (it would, if the per-press error came from where on
the pad the finger pressed).

``dropout-shift``: on contact windows of a dataset (optionally one split of a
training run's split.json), the ratio of predicted to true total force with the
model in evaluation mode and with its dropout on, each with and without the
training input noise. A gap between the two means training and inference run
different networks (dropout before instance norm shifts the output scale).

Usage::

    .venv/bin/python benchmarks/force_gain.py press-gain --data test.h5 --eval eval/
    .venv/bin/python benchmarks/force_gain.py spatial-gain --data p100.h5 --eval ev100/
    .venv/bin/python benchmarks/force_gain.py dropout-shift --checkpoint runs/s4/best.pt \\
        --data train.h5 --split-file runs/s4/split.json --split train
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np
import torch

from beadsight.checkpoint import load_checkpoint
from beadsight.data.dataset import open_dataset
from beadsight.data.splits import window_ends
from beadsight.geometry import total_force_n
from beadsight.inference.machine import cpu_summary


def _presses(data: str, eval_dir: str):
    """(predicted, true force per frame, press id per frame, contact mask,
    press ids, each press's gain = predicted / true force over its contact frames,
    each press's mean finger position in mm)."""
    predictions = Path(eval_dir) / "predictions.h5"
    if not predictions.is_file():
        sys.exit(f"{predictions}: not found; expected a 'beadsight evaluate --out' folder")
    with h5py.File(predictions, "r") as p:
        index, pred, true = p["index"][:], p["force_pred_n"][:], p["force_gt_n"][:]
    with open_dataset(data) as ds:
        press, position = ds.press_id[index], ds.position_mm[index]
    contact = true > 0
    ids = np.unique(press[contact])
    gains, xy = np.empty(len(ids)), np.empty((len(ids), 2))
    for i, k in enumerate(ids):
        m = (press == k) & contact
        gains[i] = pred[m].sum() / true[m].sum()
        xy[i] = position[m].mean(axis=0)
    return pred, true, press, contact, ids, gains, xy


def _error(pred, true, mask) -> float:
    return 100 * np.abs(pred - true)[mask].sum() / true[mask].sum()


def _divided(pred, press, ids, scale) -> np.ndarray:
    out = pred.copy()
    for k, s in zip(ids, scale, strict=True):
        out[press == k] /= s
    return out


def press_gain(data: str, eval_dir: str) -> None:
    pred, true, press, contact, ids, g, _ = _presses(data, eval_dir)
    print(f"{len(g)} presses, {contact.sum()} contact frames")
    print(f"  per-press gain: mean {g.mean():.3f}, std {g.std():.3f}")
    print(
        f"  force error {_error(pred, true, contact):.1f} %; each press divided by its gain "
        f"{_error(_divided(pred, press, ids, g), true, contact):.1f} %"
    )


def spatial_gain(data: str, eval_dir: str, train_presses: int, sigmas_mm: list[float]) -> None:
    """Can a force-gain map over the pad, fitted on the first presses, fix the later ones?
    Each later press is divided by the Gaussian-kernel mean of the earlier presses' log gains
    around its position (and, for comparison, by their overall mean or its own gain)."""
    pred, true, press, contact, ids, g, xy = _presses(data, eval_dir)
    train, test = ids < train_presses, ids >= train_presses
    if not train.any() or not test.any():
        sys.exit(f"spatial-gain: need presses below and from {train_presses} in {eval_dir}")
    log_g = np.log(g[train])
    mask = np.isin(press, ids[test]) & contact
    n = int(test.sum())

    def error(scale) -> float:
        return _error(_divided(pred, press, ids[test], scale), true, mask)

    print(f"presses 0-{train_presses - 1} fit, {n} later presses scored ({mask.sum()} frames):")
    print(
        f"  no correction {error(np.ones(n)):.1f} %; "
        f"one gain for the pouch {error(np.full(n, np.exp(log_g.mean()))):.1f} %; "
        f"each press's own gain {error(g[test]):.1f} %"
    )
    for sigma in sigmas_mm:
        d2 = ((xy[test, None, :] - xy[None, train, :]) ** 2).sum(-1)
        w = np.exp(-d2 / (2 * sigma**2))
        local = (w * log_g).sum(1) / np.maximum(w.sum(1), 1e-12)
        r = np.corrcoef(local, np.log(g[test]))[0, 1]
        print(
            f"  gain map, kernel {sigma:g} mm: {error(np.exp(local)):.1f} % "
            f"(correlation of mapped and actual log gain {r:.2f})"
        )


@torch.no_grad()
def dropout_shift(args: argparse.Namespace) -> None:
    torch.manual_seed(args.seed)
    model = load_checkpoint(args.checkpoint)
    module, span = model.module.eval(), model.span
    with open_dataset(args.data) as ds:
        presses = None
        if args.split_file:
            presses = np.array(json.loads(Path(args.split_file).read_text())[args.split])
        ends = window_ends(ds.press_id, ds.valid, span, presses)
        ends = ends[ds.contact[ends]]
        rng = np.random.default_rng(args.seed)
        ends = np.sort(rng.choice(ends, min(args.windows, len(ends)), replace=False))
        frames = np.stack([ds.read_frames(e - span + 1, e + 1) for e in ends])
        true = ds.force_n[ends]
    x = module.normalize(torch.from_numpy(frames))
    print(f"{len(ends)} contact windows of {args.data}; predicted / true total force:")
    for dropout in (False, True):
        for noise in (0.0, args.noise_std):
            module.net.train(dropout)
            y = module.net(x + noise * torch.randn_like(x))[:, 0] * module.output_scale_kpa
            ratio = total_force_n(y.numpy(), model.geometry).sum() / true.sum()
            print(f"  dropout {'on ' if dropout else 'off'}, input noise {noise:g}: {ratio:.3f}")
    module.eval()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("press-gain")
    p.add_argument("--data", required=True, help="the dataset that was evaluated")
    p.add_argument("--eval", required=True, help="the beadsight evaluate output folder")
    m = sub.add_parser("spatial-gain")
    m.add_argument("--data", required=True, help="the dataset that was evaluated")
    m.add_argument("--eval", required=True, help="the beadsight evaluate output folder")
    m.add_argument("--train-presses", type=int, default=30, help="presses that fit the map")
    m.add_argument("--sigma-mm", type=float, nargs="+", default=[3.0, 6.0])
    d = sub.add_parser("dropout-shift")
    d.add_argument("--checkpoint", required=True)
    d.add_argument("--data", required=True)
    d.add_argument("--split-file", help="a training run's split.json")
    d.add_argument("--split", default="train", choices=("train", "val", "test"))
    d.add_argument("--windows", type=int, default=256)
    d.add_argument("--noise-std", type=float, default=0.05)
    d.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)
    if args.command == "press-gain":
        press_gain(args.data, args.eval)
    elif args.command == "spatial-gain":
        spatial_gain(args.data, args.eval, args.train_presses, args.sigma_mm)
    else:
        dropout_shift(args)


if __name__ == "__main__":
    main()
