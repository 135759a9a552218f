"""Where a model's total-force error comes from: per-press gain and dropout's scale shift.

``press-gain``: from a ``beadsight evaluate`` folder's predictions.h5, the ratio
of predicted to true total force of each press (over its contact frames), its
mean and standard deviation, and the force error left once each press is divided
by its own ratio (what a model that reads every press's stiffness right would
score).

``dropout-shift``: on contact windows of a dataset (optionally one split of a
training run's split.json), the ratio of predicted to true total force with the
model in evaluation mode and with its dropout on, each with and without the
training input noise. A gap between the two means training and inference run
different networks (dropout before instance norm shifts the output scale).

Usage::

    .venv/bin/python benchmarks/force_gain.py press-gain --data test.h5 --eval eval/
    .venv/bin/python benchmarks/force_gain.py dropout-shift --checkpoint runs/s4/best.pt \\
        --data train.h5 --split-file runs/s4/split.json --split train
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np
import torch

from beadsight.checkpoint import load_checkpoint
from beadsight.data.dataset import open_dataset
from beadsight.data.splits import window_ends
from beadsight.geometry import total_force_n


def press_gain(data: str, eval_dir: str) -> None:
    with h5py.File(f"{eval_dir}/predictions.h5", "r") as p:
        index, pred, true = p["index"][:], p["force_pred_n"][:], p["force_gt_n"][:]
    with open_dataset(data) as ds:
        press = ds.press_id[index]
    contact = true > 0
    corrected, gains = pred.copy(), []
    for k in np.unique(press[contact]):
        m = (press == k) & contact
        gain = pred[m].sum() / true[m].sum()
        gains.append(gain)
        corrected[press == k] /= gain

    def error(p: np.ndarray) -> float:
        return 100 * np.abs(p - true)[contact].sum() / true[contact].sum()

    g = np.array(gains)
    print(f"{len(g)} presses, {contact.sum()} contact frames")
    print(f"  per-press gain: mean {g.mean():.3f}, std {g.std():.3f}")
    print(
        f"  force error {error(pred):.1f} %; each press divided by its gain {error(corrected):.1f} %"
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
    d = sub.add_parser("dropout-shift")
    d.add_argument("--checkpoint", required=True)
    d.add_argument("--data", required=True)
    d.add_argument("--split-file", help="a training run's split.json")
    d.add_argument("--split", default="train", choices=("train", "val", "test"))
    d.add_argument("--windows", type=int, default=256)
    d.add_argument("--noise-std", type=float, default=0.05)
    d.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.command == "press-gain":
        press_gain(args.data, args.eval)
    else:
        dropout_shift(args)


if __name__ == "__main__":
    main()
