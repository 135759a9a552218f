"""How low can the total-force error go on the simulated sensor?

Runs a simulated session without rendering and scores, with the metric of
``beadsight evaluate`` (mean |F - F_label| / mean F_label over contact frames),
predictors that know things no camera model is given:

* the true force on the finger, as is, delayed, and through the best causal
  15-frame linear filter (what a model's 15-frame window could learn): the part
  of the error that the labels themselves carry (10 Hz scale, averaging, noise);
* a force law fitted to the true depth and the distance from the centre: what a
  model that reads the depth perfectly, but not the packing, the hidden per-press
  stiffness or the relaxation, could reach.

Usage::

    .venv/bin/python benchmarks/force_floor.py --presses 100 --seed 200
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from beadsight.inference.machine import cpu_summary
from beadsight.sim import SimConfig, SimulatedSession
from beadsight.sim.dataset import ScaleLog


def delayed(x: np.ndarray, frames: int) -> np.ndarray:
    return np.concatenate([np.zeros(frames), x[: len(x) - frames]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presses", type=int, default=100)
    parser.add_argument("--seed", type=int, default=200)
    args = parser.parse_args()
    print(cpu_summary(), file=sys.stderr if getattr(args, "json", False) else sys.stdout)

    cfg = SimConfig()
    log, t, true_f, depth, radius = ScaleLog(), [], [], [], []
    for frame in SimulatedSession(cfg, args.seed, args.presses, render=False):
        log.add(frame.scale_readings)
        t.append(frame.timestamp_s)
        true_f.append(frame.true_force_n)
        depth.append(frame.finger_depth_mm)
        radius.append(float(np.hypot(*frame.finger_xy_mm)))
    true_f, radius = np.array(true_f), np.array(radius)
    label, valid = log.at(np.array(t))
    contact = valid & (true_f > 0)

    def error_pct(pred: np.ndarray) -> float:
        return 100 * np.abs(pred - label)[contact].sum() / label[contact].sum()

    def fitted(features: list[np.ndarray]) -> np.ndarray:
        x = np.stack(features, axis=1)
        w, *_ = np.linalg.lstsq(x[contact], label[contact], rcond=None)
        return x @ w

    print(f"{args.presses} presses (seed {args.seed}), {contact.sum()} contact frames")
    print(f"  true force, as is                        {error_pct(true_f):5.1f} %")
    for k in (1, 2):
        print(
            f"  true force, {k} frame(s) late              {error_pct(delayed(true_f, k)):5.1f} %"
        )
    taps = [delayed(true_f, k) for k in range(15)]
    print(f"  true force, best causal 15-frame filter  {error_pct(fitted(taps)):5.1f} %")
    law = np.array([cfg.equilibrium_force_n(d) for d in depth])
    features = [delayed(law, 1), delayed(law, 1) * radius, delayed(law, 1) * radius**2]
    features += [law, delayed(law, 2)]
    print(f"  force law of true depth and radius       {error_pct(fitted(features)):5.1f} %")


if __name__ == "__main__":
    main()
