"""The calibration's plan of its time and the fine-tuning candidates run within it.

:func:`plan_frames` splits the time left after the setup and the zero-press stage
explicitly: :data:`VAL_SHARE` for the early-stopping evaluations (which sets how many
early-stopping frames each candidate is scored on), :data:`FINAL_SHARE` for the final
stage (the test evaluations and the report), the rest for training, shared among the
fine-tuning candidates by :data:`~beadsight.calibrate.config.CANDIDATE_SHARES`.
:func:`fine_tune_candidates` trains them one after the other; a candidate whose share
cannot buy :data:`~beadsight.calibrate.config.MIN_CANDIDATE_S` of training is skipped
(the last in the order first), and its time goes to the others.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path

from beadsight.calibrate.budget import Budget
from beadsight.calibrate.candidates import (
    Candidate,
    candidate_config,
    figures,
    timed_evaluate,
    train_candidate,
)
from beadsight.calibrate.config import (
    ALIGNED_FILE,
    CANDIDATE_SHARES,
    FINE_TUNED,
    MIN_CANDIDATE_S,
    SCRATCH_MIN_TRAIN_PRESSES,
    CalibrateConfig,
)
from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.train.config import TrainConfig

logger = logging.getLogger(__name__)

VAL_SHARE = 0.25  # of the time left: the early-stopping evaluations
VAL_MIN_FRAMES = 16  # fewer early-stopping frames only where two evaluations of these do not fit
FINAL_SHARE = 0.2  # of the time left: the test evaluations, model.pt and the report
VAL_MAX_FRAMES = 256  # early-stopping presses: at most this many frames, spread evenly
SETUP_GUESS_S = 8.0  # a fine-tuning's setup (loading its windows) before one is measured


def applicable(config: CalibrateConfig, train_presses: int) -> dict[str, str | None]:
    """For each fine-tuning candidate: None if it makes sense for the data, else why not."""
    why = {}
    for name in FINE_TUNED:
        if name not in config.candidates:
            why[name] = "not in --candidates"
        elif name == "scratch" and train_presses < SCRATCH_MIN_TRAIN_PRESSES:
            why[name] = (
                f"{train_presses} training presses; a model from scratch needs at least "
                f"{SCRATCH_MIN_TRAIN_PRESSES}"
            )
        else:
            why[name] = None
    return why


def plan_frames(budget: Budget, config: CalibrateConfig, data: dict) -> dict:
    """How many early-stopping frames each candidate is scored on, and the time planned
    for each stage (seconds), recorded in metrics.json."""
    left = budget.left()
    reasons = applicable(config, len(data["split"]["train"]))
    tuned = [n for n, why in reasons.items() if why is None]
    # zero-shot and zero-press, then each fine-tuning's kept checkpoint (the trainer's own
    # validations are paid from the candidate's share)
    evaluations = 2 + len(tuned)
    val_s = VAL_SHARE * left
    available = data["windows"]["val"]
    frames = budget.frames_within(val_s, min(VAL_MAX_FRAMES, available), evaluations)
    floor = min(VAL_MIN_FRAMES, available)
    if frames < floor and 2 * budget.evaluation_s(floor) <= 2 * val_s:
        frames = floor
    return {
        "left_s": round(left, 1),
        "val_frames": max(frames, 1),
        "val_s": round(val_s, 1),
        "final_s": round(FINAL_SHARE * left, 1),
        "training_s": round(left * (1 - VAL_SHARE - FINAL_SHARE), 1),
        "not_applicable": {n: why for n, why in reasons.items() if why},
        "shares": {n: CANDIDATE_SHARES[n] for n in tuned},
    }


def _start(cands: dict[str, Candidate], config: CalibrateConfig) -> str:
    """The model fine-tuning starts from: zero-shot or zero-press, the lower early-stopping
    MAE (zero-press only where --candidates lists it)."""
    names = [n for n in ("zero-press", "zero-shot") if cands[n].val is not None]
    names = [n for n in names if n == "zero-shot" or n in config.candidates]
    return min(names, key=lambda n: (cands[n].val["mae_kpa"], names.index(n)))


def fine_tune_candidates(
    cands: dict[str, Candidate],
    config: CalibrateConfig,
    base: PressureModel,
    base_path: Path,
    out: Path,
    budget: Budget,
    plan: dict,
    data: dict,
) -> None:
    """Train the applicable fine-tuning candidates in their shares of the time, score each
    kept checkpoint on the early-stopping frames; adds them to ``cands``."""
    start = _start(cands, config)
    start_path = out / ALIGNED_FILE if start == "zero-press" else base_path
    for name, why in plan["not_applicable"].items():
        cands[name] = Candidate(name).skip(why)
    remaining = list(plan["shares"])
    setup_s = SETUP_GUESS_S
    val_frames = plan["val_frames"]
    while remaining:
        name = remaining[0]
        score_s = budget.evaluation_s(val_frames)
        left = budget.left() - plan["final_s"] - score_s * len(remaining)
        share = left * plan["shares"][name] / sum(plan["shares"][n] for n in remaining)
        end_s = 2 * score_s  # the trainer's last validation (and one timed just before it)
        needed = MIN_CANDIDATE_S + setup_s + end_s
        if share < needed:
            dropped = remaining.pop()
            cands[dropped] = Candidate(dropped).skip(
                f"no time: {max(left, 0):.0f} s of training left for {len(remaining) + 1} "
                f"candidate(s), a share of {max(share, 0):.0f} s where {needed:.0f} s are "
                "needed (a larger --budget-min)"
            )
            continue
        remaining.pop(0)
        cand = cands[name] = Candidate(name, start=None if name == "scratch" else start)
        cand.budget_s = share
        t0 = time.monotonic()
        tc = candidate_config(name, config, base, start_path, out)
        tc = with_val_stride(tc, data["windows"]["val"], val_frames)
        with budget.stage(f"training {name}"):
            best, info = train_candidate(tc, t0 + share - score_s, end_s)
        setup_s = info["setup_s"]
        cand.steps, cand.best_step = int(info["steps"]), info["best_step"]
        if best is None:
            cand.skip(f"its setup took {info['setup_s']:.0f} s, all of its {share:.0f} s")
            continue
        cand.model = load_checkpoint(best)
        with budget.stage("early-stopping evaluations"):
            cand.val = figures(
                timed_evaluate(budget, cand.model, config, data["split"]["val"], val_frames)
            )
        cand.seconds, cand.status = time.monotonic() - t0, "scored"
        logger.info(
            "candidate %s: %d steps in %.0f s (share %.0f s), early-stopping MAE %.4f kPa",
            name,
            cand.steps,
            cand.seconds,
            share,
            cand.val["mae_kpa"],
        )


def with_val_stride(tc: TrainConfig, val_windows: int, val_frames: int) -> TrainConfig:
    """The trainer validates on about ``val_frames`` of the ``val_windows`` windows."""
    return dataclasses.replace(tc, val_stride=max(1, math.ceil(val_windows / max(val_frames, 1))))
