"""``beadsight calibrate``: fit a base model to a new pouch, within one wall-clock budget.

1. check the data (enough presses, contact frames, an image size the base model fits);
   split the presses used (after dropping ``skip`` break-in presses) by press into
   train / early-stopping / test (:data:`CALIBRATION_SPLIT`, seeded). With
   ``presses=0`` no press is used: every press of ``data`` is a test press, and with no
   ``data`` (a rest file only) nothing is scored;
2. the rest reference and the zero-press candidate (:mod:`beadsight.calibrate.align`);
3. the candidates (:mod:`beadsight.calibrate.candidates`) scored on the early-stopping
   presses: zero-shot, zero-press, then the fine-tunings that make sense for the data
   and fit in the budget, each in its share of the training time;
4. the best by the early-stopping presses' MAE becomes ``model.pt`` (optionally with a
   force gain); it and then the others are scored on the test presses, as many frames as
   the time left allows; ``metrics.json``, the learning curve and ``report.html``.

The budget (:class:`~beadsight.calibrate.budget.Budget`) counts everything; stages that
do not fit are left out or shortened, and the record says which.
"""

from __future__ import annotations

import logging
import math
import shutil
import time
from pathlib import Path

import numpy as np

from beadsight.assets import BASE_MODEL, shipped_model_path
from beadsight.calibrate.align import (
    RestFrames,
    align_to_rest,
    fit_force_gain,
    rest_from_data,
    rest_from_file,
    with_meta,
)
from beadsight.calibrate.budget import Budget
from beadsight.calibrate.candidates import Candidate, figures, timed_evaluate
from beadsight.calibrate.config import (
    ALIGNED_FILE,
    CALIBRATION_SPLIT,
    FINE_TUNED,
    MIN_PRESSES,
    MODEL_FILE,
    RECOMMENDED_PRESSES,
    REST_FILE,
    TRAIN_FOLDER,
    CalibrateConfig,
)
from beadsight.calibrate.tuning import fine_tune_candidates, plan_frames
from beadsight.checkpoint import PressureModel, load_checkpoint
from beadsight.config import ConfigError, ContactThresholds
from beadsight.data.dataset import DatasetError, dataset_fingerprint, open_dataset
from beadsight.data.rest import RestReference
from beadsight.data.splits import dataset_window_ends, split_presses
from beadsight.files import prepare_output_folder
from beadsight.train.config import SIZE_MULTIPLE

logger = logging.getLogger(__name__)

REPORT_RESERVE_S = 4.0  # writing model.pt, metrics.json, the learning curve and the report
CHOICE_ORDER = ("zero-press", "zero-shot", "decoder", "all", "scratch")  # ties: the first


def base_checkpoint(base: str | None) -> Path:
    """The checkpoint a calibration starts from: ``base``, or the shipped base model
    (``beadsight/assets/base_model.pt``, see its ``base_model.md``)."""
    if base is not None:
        return Path(base)
    return shipped_model_path(BASE_MODEL)


def prepare_out(out: Path, overwrite: bool) -> None:
    """Refuse a ``out`` that is a file, or a folder that is not empty, unless ``overwrite``
    (then an earlier calibration's fine-tuning runs are removed)."""
    prepare_output_folder(out, overwrite)
    if (out / TRAIN_FOLDER).is_dir():
        shutil.rmtree(out / TRAIN_FOLDER)


def used_split(config: CalibrateConfig, num_presses: int) -> dict[str, np.ndarray]:
    """The presses used (``presses`` of them after the first ``skip``), split by press with
    ``seed``; with ``presses=0`` all of them are test presses."""
    first = config.skip
    if config.zero_press:
        empty = np.zeros(0, dtype=np.int64)
        return {"train": empty, "val": empty, "test": np.arange(first, num_presses)}
    stop = num_presses if config.presses is None else min(first + config.presses, num_presses)
    split = split_presses(stop - first, CALIBRATION_SPLIT, config.seed)
    return {name: ids + first for name, ids in split.items()}


def check_data(config: CalibrateConfig, base: PressureModel) -> dict:
    """The split of the presses used and their window counts, after checking that the
    data can calibrate ``base``."""
    with open_dataset(config.data) as ds:
        if not ds.contact.any():
            raise DatasetError(
                f"{ds.path}: no contact frames (field 'force' never reaches the contact "
                f"threshold of {ContactThresholds().contact_n:.2f} N); calibration needs presses: "
                "check the scale's readings"
            )
        ds.require_presses()
        available = max(min(ds.num_presses - config.skip, config.presses or ds.num_presses), 0)
        needed = 1 if config.zero_press else MIN_PRESSES
        if available < needed:
            raise DatasetError(
                f"{ds.path}: {available} presses to calibrate on ({ds.num_presses} in the file, "
                f"--skip {config.skip}); calibration needs at least {MIN_PRESSES} (one each to "
                f"train on, to stop early on and to test on), and {RECOMMENDED_PRESSES} or more "
                "for a useful model (--presses 0 scores on every press and needs one)"
            )
        if ds.image_size < base.image_size or ds.image_size % SIZE_MULTIPLE:
            raise ConfigError(
                f"image size {ds.image_size} px of {ds.path} does not fit the base model "
                f"{base.source} ({base.image_size} px): the frames must be at least "
                f"{base.image_size} px and a multiple of {SIZE_MULTIPLE} (they are resized to "
                f"{base.image_size} px); process the recording with --image-size {base.image_size}"
            )
        split = used_split(config, int(ds.num_presses))
        rest = bool(base.rest)
        windows = {
            k: int(dataset_window_ends(ds, base.span, v, rest=rest).size) for k, v in split.items()
        }
        return {
            "split": split,
            "windows": windows,
            "num_presses": int(ds.num_presses),
            "fingerprint": dataset_fingerprint(ds),
            "image_size": int(ds.image_size),
        }


def zero_press(config: CalibrateConfig, base: PressureModel, data: dict | None) -> RestFrames:
    """The new pouch's rest frames: the rest file, else the pre-contact frames of the
    training presses (with ``presses=0``: of every press used)."""
    if config.rest:
        return rest_from_file(config.rest, base.image_size)
    split = data["split"]
    ids = split["test"] if config.zero_press else split["train"]
    return rest_from_data(config.data, ids, base.image_size)


def calibrate(config: CalibrateConfig, started: float | None = None) -> dict:
    """Calibrate as ``config`` says (module doc); returns the metrics dict of metrics.json.
    ``started``: when the command started (``time.monotonic()``), the budget's start."""
    budget = Budget(config.budget_min, started)
    out = Path(config.out)
    if config.zero_press and "zero-press" not in config.candidates:
        raise ConfigError(
            "--presses 0 calibrates from rest frames only: keep the zero-press "
            "candidate in --candidates"
        )
    with budget.stage("setup"):
        base_path = base_checkpoint(config.base)
        base = load_checkpoint(base_path)
        data = check_data(config, base) if config.data else None
        prepare_out(out, config.overwrite)
    with budget.stage("zero-press"):
        rest = zero_press(config, base, data)
        aligned, align_record = align_to_rest(base, rest)
        aligned.save(out / ALIGNED_FILE)
        if rest.image is not None:
            RestReference(rest.image, int(align_record["count"]), origin="given").save(
                out / REST_FILE
            )
    cands = {
        "zero-shot": Candidate("zero-shot", base),
        "zero-press": Candidate("zero-press", aligned),
    }
    record = {
        "config": config.to_dict(),
        "base": str(base_path.resolve()),
        "alignment": align_record,
        "rest_file": REST_FILE if rest.image is not None else None,
        "presses_used": 0,
        "force_gain": 1.0,
    }
    if data is None:
        return _finish(config, out, budget, cands, "zero-press", record, None, base_path)
    split = data["split"]
    record["presses"] = {k: [int(i) for i in v] for k, v in split.items()}
    record["presses_used"] = int(len(split["train"]) + len(split["val"]))
    logger.info(
        "calibrating %s on %s: %d train, %d early-stopping, %d test presses",
        base_path,
        config.data,
        *(len(split[k]) for k in ("train", "val", "test")),
    )
    if config.zero_press:
        chosen = "zero-press"
    else:
        plan = plan_frames(budget, config, data)
        record["plan"] = plan
        for name in ("zero-shot", "zero-press"):
            cand = cands[name]
            with budget.stage("early-stopping evaluations"):
                t0 = time.monotonic()
                cand.val = figures(
                    timed_evaluate(budget, cand.model, config, split["val"], plan["val_frames"])
                )
                cand.seconds, cand.status = time.monotonic() - t0, "scored"
        fine_tune_candidates(cands, config, base, base_path, out, budget, plan, data)
        chosen = choose(cands, config)
    return _finish(config, out, budget, cands, chosen, record, data, base_path)


def choose(cands: dict[str, Candidate], config: CalibrateConfig) -> str:
    """The candidate with the lowest MAE on the early-stopping presses (zero-shot always
    eligible; the others where ``config.candidates`` lists them)."""
    eligible = [
        n
        for n in CHOICE_ORDER
        if n in cands and cands[n].val is not None and (n == "zero-shot" or n in config.candidates)
    ]
    chosen = min(eligible, key=lambda n: (cands[n].val["mae_kpa"], eligible.index(n)))
    logger.info(
        "kept %s (early-stopping MAE %s)",
        chosen,
        {n: round(cands[n].val["mae_kpa"], 4) for n in eligible},
    )
    return chosen


def _finish(config, out, budget, cands, chosen, record, data, base_path) -> dict:
    """The force gain, model.pt, the test evaluations that fit, metrics.json and report."""
    from beadsight.calibrate.report import write_outputs

    model = cands[chosen].model
    with budget.stage("final"):
        split = data["split"] if data else None
        if config.gain and data and not config.zero_press:
            left = budget.left() - REPORT_RESERVE_S - 2 * budget.evaluation_s(1)
            frames = budget.frames_within(left / 2, 512)
            if frames:
                record["force_gain"] = fit_force_gain(model, config.data, split["train"], frames)
            else:
                record["force_gain_note"] = "not fitted: the budget ran out"
        model = finished_model(model, config, data, base_path, record, chosen)
        model.save(out / MODEL_FILE)
        final = test_evaluations(config, out, budget, cands, chosen, data) if data else None
    record["chosen"] = chosen
    order = ("zero-shot", "zero-press", *FINE_TUNED)
    record["candidates"] = {n: cands[n].record() for n in order if n in cands}
    record["fine_tuned"] = any(c.steps > 0 for c in cands.values())
    record["budget"] = budget.record()
    record["seconds"] = record["budget"]["seconds"]
    return write_outputs(out, final, cands, chosen, record)


def test_evaluations(config, out, budget, cands, chosen, data) -> dict | None:
    """The kept model (model.pt, with the output files) and then the other scored
    candidates on the same test frames, as many as the time left allows."""
    split, available = data["split"], data["windows"]["test"]
    others = [n for n in CHOICE_ORDER if n != chosen and cands.get(n) and cands[n].model]
    left = budget.left() - REPORT_RESERVE_S
    frames = budget.frames_within(left / (1 + len(others)), available)
    frames = frames or budget.frames_within(left, available)
    if not frames:
        logger.warning("no time left to score the calibrated model on the test presses")
        return None
    final = timed_evaluate(
        budget,
        out / MODEL_FILE,
        config,
        split["test"],
        frames,
        out_dir=out,
        report=False,
        train_presses=split["train"],
        plots=True,
    )
    cands[chosen].test = figures(final)
    for name in others:
        if budget.evaluation_s(frames) > budget.left() - REPORT_RESERVE_S:
            cands[name].notes.append("not scored on the test presses: the budget ran out")
            continue
        metrics = timed_evaluate(budget, cands[name].model, config, split["test"], frames)
        cands[name].test = figures(metrics)
    return final


def finished_model(
    model: PressureModel,
    config: CalibrateConfig,
    data: dict | None,
    base: Path,
    record: dict,
    chosen: str,
) -> PressureModel:
    """``model`` with the force gain in its output scale, the split (so ``beadsight evaluate
    --split test`` scores the same presses) and the calibration in its metadata."""
    training = {**(model.meta.training or {}), "calibration": {**record, "chosen": chosen}}
    if data is not None:
        split = data["split"]
        training.update(
            dataset_path=str(Path(config.data).resolve()),
            dataset_fingerprint=data["fingerprint"],
            split={
                **{k: [int(i) for i in v] for k, v in split.items()},
                "num_presses": data["num_presses"],
            },
            split_fractions=list(CALIBRATION_SPLIT),
            split_seed=config.seed,
        )
    provenance = {
        **model.meta.provenance,
        "source": "beadsight calibrate",
        "base": str(base.resolve()),
    }
    scale = float(model.meta.output_scale_kpa) * float(record["force_gain"])
    if not math.isfinite(scale):
        raise ConfigError(f"force gain {record['force_gain']!r} gives no finite output scale")
    return with_meta(model, output_scale_kpa=scale, training=training, provenance=provenance)
