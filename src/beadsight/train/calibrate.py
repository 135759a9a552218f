"""``beadsight calibrate``: fit a base model to a new sensor from a few of its presses.

The stages, within one wall-clock budget (``CalibrateConfig.budget_min``):

1. check the data (enough presses, contact frames, an image size the base model fits);
   split the presses used (after dropping ``skip`` break-in presses) by press into
   train / early-stopping / test (:data:`CALIBRATION_SPLIT`, seeded);
2. score the base model as it comes (zero-shot) on the test presses;
3. zero-press alignment (:func:`beadsight.train.align.align_to_rest`), scored again;
4. fine-tune (``layers`` all or decoder) with the trainer under the budget left, from
   the base or the aligned model (the lower MAE on the early-stopping presses),
   validating on the early-stopping presses and keeping the best checkpoint (the
   starting weights included);
5. optionally a force gain (:func:`beadsight.train.align.fit_force_gain`);
6. ``model.pt``, the evaluation of it on the test presses (every frame with a full
   window of real history, across press boundaries), ``metrics.json`` with all three
   stages, the learning curve and ``report.html``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shutil
import time
from pathlib import Path
from typing import Any

from beadsight.checkpoint import (
    BASE_MODEL,
    PressureModel,
    load_checkpoint,
    shipped_model_path,
)
from beadsight.config import ConfigError, ContactThresholds
from beadsight.data.dataset import DatasetError, open_dataset
from beadsight.data.splits import dataset_window_ends
from beadsight.evaluation.config import EvaluateConfig
from beadsight.evaluation.evaluate import evaluate
from beadsight.train.align import align_to_rest, fit_force_gain, with_meta
from beadsight.train.calibrate_config import (
    ALIGNED_FILE,
    CALIBRATION_SPLIT,
    METRICS_FILE,
    MIN_PRESSES,
    MODEL_FILE,
    RECOMMENDED_PRESSES,
    REPORT_FILE,
    TRAIN_FOLDER,
    CalibrateConfig,
)
from beadsight.train.config import SIZE_MULTIPLE, TrainConfig
from beadsight.train.prepare import split_used_presses
from beadsight.train.run import BEST_CHECKPOINT
from beadsight.train.windows import dataset_fingerprint

logger = logging.getLogger(__name__)

SECONDS_PER_MIN = 60.0
FINAL_RESERVE = 1.5  # the final evaluation (with plots) takes about this many zero-shot ones
REPORT_RESERVE_S = 5.0  # writing model.pt, plots and the report
MIN_TRAIN_S = 3.0  # fine-tune at least this long, even past the budget
VAL_MAX_WINDOWS = 256  # early stopping validates on at most about this many windows
RUN_EPOCHS = 1_000_000  # the budget, not the epoch count, ends the fine-tuning
STAGE_KEYS = (
    "mae_kpa",
    "force_error_pct",
    "cop_error_mm",
    "iou",
    "worst_region_mae_kpa",
    "frames",
    "presses",
    "coverage",
    "window_coverage",
)


def base_checkpoint(base: str | None) -> Path:
    """The checkpoint a calibration starts from: ``base``, or the shipped base model
    (``beadsight/assets/base_model.pt``, see its ``base_model.md``)."""
    if base is not None:
        return Path(base)
    return shipped_model_path(BASE_MODEL)


def prepare_out(out: Path, overwrite: bool) -> None:
    """Refuse to write over an earlier calibration unless ``overwrite`` (then remove its files)."""
    names = (MODEL_FILE, ALIGNED_FILE, METRICS_FILE, REPORT_FILE, TRAIN_FOLDER)
    present = [n for n in names if (out / n).exists()]
    if present and not overwrite:
        raise ConfigError(
            f"out {out} already holds a calibration ({', '.join(present)}); pass --overwrite "
            "to replace it, or choose another --out"
        )
    if (out / TRAIN_FOLDER).is_dir():
        shutil.rmtree(out / TRAIN_FOLDER)
    out.mkdir(parents=True, exist_ok=True)


def train_config(config: CalibrateConfig, base: PressureModel, base_path: Path) -> TrainConfig:
    """The fine-tuning's TrainConfig: the base model's shape, the recipe, this run's presses."""
    m = base.meta.model
    return TrainConfig(
        data=config.data,
        out=str(Path(config.out) / TRAIN_FOLDER),
        init=str(base_path),
        frames=m.frames,
        frame_stride=m.frame_stride,
        width=m.width,
        up_kernel=m.up_kernel,
        dropout=m.dropout,
        rest_input=m.rest_input,
        image_size=base.image_size,
        epochs=RUN_EPOCHS,
        budget_min=config.budget_min,
        val_every_min=config.val_every_min,
        lr=config.lr,
        lr_min=config.lr_min,
        lr_schedule="cosine",
        batch_size=config.batch_size,
        noise_std=config.noise_std,
        augment=config.augment,
        split=CALIBRATION_SPLIT,
        seed=config.seed,
        presses=config.presses,
        skip_presses=config.skip,
        train_layers="decoder" if config.layers == "decoder" else "all",
        device=config.device,
        progress=config.progress,
        log_every_steps=10,
        val_at_start=True,
        checkpoint_every_min=1e6,
    )


def check_data(config: CalibrateConfig, base: PressureModel, tc: TrainConfig) -> dict[str, Any]:
    """The split of the presses used, after checking that the data can calibrate ``base``."""
    with open_dataset(config.data) as ds:
        if not ds.contact.any():
            raise DatasetError(
                f"{ds.path}: no contact frames (field 'force' never reaches the contact "
                f"threshold of {ContactThresholds().contact_n:.2f} N); calibration needs presses: "
                "check the scale's readings"
            )
        available = max(min(ds.num_presses - config.skip, config.presses or ds.num_presses), 0)
        if available < MIN_PRESSES:
            raise DatasetError(
                f"{ds.path}: {available} presses to calibrate on ({ds.num_presses} in the file, "
                f"--skip {config.skip}); calibration needs at least {MIN_PRESSES} (one each to "
                f"train on, to stop early on and to test on), and {RECOMMENDED_PRESSES} or more "
                "for a useful model"
            )
        if ds.image_size < base.image_size or ds.image_size % SIZE_MULTIPLE:
            raise ConfigError(
                f"image size {ds.image_size} px of {ds.path} does not fit the base model "
                f"{base.source} ({base.image_size} px): the frames must be at least "
                f"{base.image_size} px and a multiple of {SIZE_MULTIPLE} (they are resized to "
                f"{base.image_size} px); process the recording with --image-size {base.image_size}"
            )
        split = split_used_presses(tc, ds)
        val_windows = dataset_window_ends(ds, tc.span, split["val"], rest=tc.rest_input).size
        return {
            "split": split,
            "val_stride": max(1, math.ceil(val_windows / VAL_MAX_WINDOWS)),
            "num_presses": int(ds.num_presses),
            "fingerprint": dataset_fingerprint(ds),
            "image_size": int(ds.image_size),
        }


def score(
    model: PressureModel | Path,
    config: CalibrateConfig,
    split: dict,
    out_dir: Path | None = None,
    **settings,
) -> dict:
    """Metrics of ``model`` on the test presses (every frame with a full window);
    ``settings``: fields of :class:`~beadsight.evaluation.config.EvaluateConfig`."""
    return evaluate(
        model,
        config.data,
        EvaluateConfig(resize=True, device=config.device, progress=config.progress, **settings),
        out_dir,
        presses=split["test"],
        train_presses=split["train"],
    )


def stage(metrics: dict) -> dict:
    return {k: metrics.get(k) for k in STAGE_KEYS}


def calibrate(config: CalibrateConfig) -> dict:
    """Calibrate as ``config`` says (module doc); returns the metrics dict of metrics.json."""
    t0 = time.monotonic()
    out = Path(config.out)
    base_path = base_checkpoint(config.base)
    base = load_checkpoint(base_path)
    tc = train_config(config, base, base_path)
    data = check_data(config, base, tc)
    prepare_out(out, config.overwrite)
    split = data["split"]
    logger.info(
        "calibrating %s on %s: %d train, %d early-stopping, %d test presses",
        base_path,
        config.data,
        *(len(split[k]) for k in ("train", "val", "test")),
    )
    t_eval = time.monotonic()
    stages = {"zero_shot": stage(score(base, config, split, plots=False))}
    t_eval = time.monotonic() - t_eval
    aligned, align_record = align_to_rest(base, config.data, config.rest, split["train"])
    aligned.save(out / ALIGNED_FILE)
    stages["aligned"] = stage(score(aligned, config, split, plots=False))
    model, trained = aligned, None
    if config.layers != "none":
        start_path = fine_tune_start(base, base_path, aligned, out, config, split, align_record)
        left = config.budget_min * SECONDS_PER_MIN - (time.monotonic() - t0)
        left -= FINAL_RESERVE * t_eval + REPORT_RESERVE_S
        tc = dataclasses.replace(tc, init=str(start_path), val_stride=data["val_stride"])
        model = fine_tune(tc, left)
        trained = model.meta.training
    gain = fit_force_gain(model, config.data, split["train"]) if config.gain else 1.0
    record = {
        "config": config.to_dict(),
        "base": str(base_path.resolve()),
        "alignment": align_record,
        "force_gain": gain,
        "presses": {k: [int(i) for i in v] for k, v in split.items()},
        "fine_tuning": _fine_tuning(trained, tc),
    }
    model = finished_model(model, config, data, base_path, record)
    model.save(out / MODEL_FILE)
    from beadsight.train.calibrate_report import write_outputs

    final = score(out / MODEL_FILE, config, split, out_dir=out, report=False)
    record["seconds"] = round(time.monotonic() - t0, 1)
    return write_outputs(out, final, stages, record)


def fine_tune_start(
    base: PressureModel,
    base_path: Path,
    aligned: PressureModel,
    out: Path,
    config: CalibrateConfig,
    split: dict,
    record: dict,
) -> Path:
    """The checkpoint fine-tuning starts from: the base model or the aligned one, whichever
    has the lower MAE on the early-stopping presses (the alignment can hurt: a dark colour
    channel's noise is amplified by its small std). Noted in ``record``."""
    maes = {}
    for name, model in (("base", base), ("aligned", aligned)):
        settings = EvaluateConfig(
            resize=True,
            device=config.device,
            progress=False,
            plots=False,
            max_frames=VAL_MAX_WINDOWS,
        )
        metrics = evaluate(model, config.data, settings, presses=split["val"])
        maes[name] = metrics["mae_kpa"]
    chosen = "aligned" if maes["aligned"] <= maes["base"] else "base"
    record.update(val_mae_kpa=maes, fine_tune_from=chosen)
    logger.info("fine-tuning starts from the %s model (early-stopping MAE %s)", chosen, maes)
    return out / ALIGNED_FILE if chosen == "aligned" else base_path


def fine_tune(tc: TrainConfig, left_s: float) -> PressureModel:
    """Train as ``tc`` says for ``left_s`` seconds (at least MIN_TRAIN_S); the best checkpoint."""
    if left_s < MIN_TRAIN_S:
        logger.warning(
            "the budget leaves %.0f s to fine-tune: fine-tuning %.0f s", left_s, MIN_TRAIN_S
        )
    from beadsight.train.trainer import train

    train(dataclasses.replace(tc, budget_min=max(left_s, MIN_TRAIN_S) / SECONDS_PER_MIN))
    return load_checkpoint(Path(tc.out) / BEST_CHECKPOINT)


def _fine_tuning(training: dict | None, tc: TrainConfig) -> dict | None:
    if training is None:
        return None
    return {
        "best": training.get("best_val"),
        "best_step": training.get("step"),
        "steps": _steps_trained(Path(tc.out)),
        "budget_min": tc.budget_min,
        "run_folder": TRAIN_FOLDER,
    }


def _steps_trained(run: Path) -> int:
    """Optimizer steps the fine-tuning took (its metrics.jsonl's last step; 0 if none)."""
    steps = 0
    log = run / "metrics.jsonl"
    if log.is_file():
        for line in log.read_text().splitlines():
            steps = max(steps, int(json.loads(line).get("step") or 0))
    return steps


def finished_model(
    model: PressureModel, config: CalibrateConfig, data: dict, base: Path, record: dict
) -> PressureModel:
    """``model`` with the force gain in its output scale, the split (so ``beadsight evaluate
    --split test`` scores the same presses) and the calibration in its metadata."""
    split = data["split"]
    training = {
        **(model.meta.training or {}),
        "dataset_path": str(Path(config.data).resolve()),
        "dataset_fingerprint": data["fingerprint"],
        "split": {
            **{k: [int(i) for i in v] for k, v in split.items()},
            "num_presses": data["num_presses"],
        },
        "split_fractions": list(CALIBRATION_SPLIT),
        "split_seed": config.seed,
        "calibration": record,
    }
    provenance = {
        **model.meta.provenance,
        "source": "beadsight calibrate",
        "base": str(base.resolve()),
    }
    scale = float(model.meta.output_scale_kpa) * float(record["force_gain"])
    return with_meta(model, output_scale_kpa=scale, training=training, provenance=provenance)
