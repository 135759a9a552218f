"""The simulator's documentation figure: frames at rest and under load, and the force trace.

``python -m beadsight.sim.figure docs/images/simulator.png`` regenerates
``docs/images/simulator.png`` (deterministic for a seed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from beadsight.config import REFERENCE_G_TO_N
from beadsight.geometry import mm_to_px
from beadsight.sim.config import SimConfig
from beadsight.sim.press import Press
from beadsight.sim.session import SimulatedSession

# The figure shows the second press (a firm one); the first, lighter one settles the pouch.
FIGURE_PRESSES = (Press(8.0, -8.0, 127.8), Press(-5.0, 6.0, 127.25))


def _pick_frames(config: SimConfig, seed: int) -> dict[str, int]:
    """Frame indices of interest in the figure's press (physics only)."""
    frames = list(SimulatedSession(config, seed, FIGURE_PRESSES, render=False))
    press = np.array([f.press_index for f in frames])
    force = np.array([f.true_force_n for f in frames])
    idx = np.flatnonzero(press == len(FIGURE_PRESSES) - 1)
    touching = idx[force[idx] > 0]
    peak = int(idx[np.argmax(force[idx])])
    return {
        "at rest": int(touching[0]) - 3,
        "loading": int(touching[0] + (peak - touching[0]) // 2),
        "peak force": peak,
        "after release": int(idx[-1]),
    }


def simulator_figure(path: str | Path, seed: int = 4, image_size: int = 256) -> Path:
    """Write a PNG: four sensor-space frames of one press, the change under load, a raw
    fisheye frame, and the press's true force beside the scale's readings."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    config = SimConfig(image_size_px=image_size)
    picks = _pick_frames(config, seed)
    wanted = {i: name for name, i in picks.items()}
    session = SimulatedSession(config, seed, FIGURE_PRESSES, render=False)
    shots: dict[str, np.ndarray] = {}
    raw = None
    trace = []
    first = 0
    for f in session:
        if f.frame_index in wanted:
            shots[wanted[f.frame_index]] = session.simulator.render()
            if wanted[f.frame_index] == "peak force":
                raw = session.simulator.render_raw()
                press_xy = f.commanded_xy_mm
        if f.press_index == len(FIGURE_PRESSES) - 1:
            first = f.frame_index if not trace else first
            trace.append((f.timestamp_s, f.true_force_n, f.scale_readings, f.phase))
    assert raw is not None

    fig = Figure(figsize=(18, 6.4), dpi=100)  # no pyplot: no global backend state
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 6, height_ratios=[1, 0.7], hspace=0.22, wspace=0.05)
    change = np.abs(shots["peak force"].astype(float) - shots["at rest"].astype(float)).mean(-1)
    panels = [
        *((name, shots[name]) for name in picks),
        ("|peak - at rest|", np.clip(change * 3, 0, 255).astype(np.uint8)),
        ("raw 1280x1024 fisheye (peak)", raw[..., ::-1]),
    ]
    centre = mm_to_px(press_xy, config.geometry)
    radius_px = config.finger_radius_mm / config.geometry.mm_per_px
    for k, (name, image) in enumerate(panels):
        ax = fig.add_subplot(grid[0, k])
        ax.imshow(image, cmap="gray" if image.ndim == 2 else None)
        ax.set_title(name, fontsize=11)
        ax.axis("off")
        if name in ("loading", "peak force", "|peak - at rest|"):
            ax.add_patch(Circle(centre[::-1], radius_px, fill=False, ls="--", lw=1, color="w"))

    ax = fig.add_subplot(grid[1, :])
    t0 = trace[0][0]
    t = np.array([x[0] for x in trace]) - t0
    ax.plot(t, [x[1] for x in trace], color="0.3", lw=1.5, label="true force on the finger")
    readings = np.array([r for x in trace for r in x[2]])
    ax.plot(
        readings[:, 0] - t0,
        readings[:, 1] * REFERENCE_G_TO_N,
        "o",
        ms=3.5,
        color="C3",
        label=f"scale readings ({config.scale_rate_hz:g} Hz; what the dataset stores)",
    )
    for i in picks.values():
        ax.axvline(t[i - first], color="C0", lw=0.8, ls=":")
    phases = [x[3] for x in trace]
    for phase in ("descend", "dwell", "rise"):
        sel = t[[p == phase for p in phases]]
        if len(sel):
            ax.axvspan(
                sel[0],
                sel[-1],
                color={"descend": "C1", "dwell": "C2", "rise": "C4"}[phase],
                alpha=0.12,
                lw=0,
            )
            ax.text(
                (sel[0] + sel[-1]) / 2,
                0.97,
                phase,
                transform=ax.get_xaxis_transform(),
                ha="center",
                va="top",
                fontsize=9,
            )
    ax.set_xlabel("time in the press cycle (s)")
    ax.set_ylabel("force (N)")
    ax.legend(loc="upper left", fontsize=9)
    ax.set_xlim(t[0], t[-1])
    fig.suptitle(
        f"Simulated BeadSight: {config.n_beads} beads, {config.n_bubbles} bubbles, "
        f"press at ({press_xy[0]:.1f}, {press_xy[1]:.1f}) mm (dashed: finger, never visible)",
        fontsize=12,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="docs/images/simulator.png")
    parser.add_argument("--seed", type=int, default=4)
    args = parser.parse_args(argv)
    print(f"wrote {simulator_figure(args.out, args.seed)}")


if __name__ == "__main__":
    main()
