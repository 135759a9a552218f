"""Which frames an evaluation scores: the split, and the frames of it with a full window.

* ``"test"`` / ``"val"`` use the press ids the training run stored in the checkpoint
  (``meta.training["split"]``) when they fit the dataset; otherwise the split is
  recomputed with :func:`beadsight.data.splits.split_presses` (with the run's
  fractions and seed when known) and a warning is logged.
* A **reference** checkpoint stores the frames it was trained and tested on
  (``train_indices`` / ``test_indices``, window-end frame indices into the file it
  was trained on). ``"test"`` scores exactly those test frames when the dataset is
  that file (its name, frame count and valid frames agree), and says so; otherwise
  ``"test"`` is refused, since a recomputed split could score the model on frames it
  was trained on. The reference keeps no validation split: ``"val"`` is refused.
* ``"all"`` uses every press.
* :func:`given_presses`: press ids the caller chose (``evaluate(..., presses=...)``).

The evaluated frames are those of the split with a full window of valid,
continuous history (:func:`beadsight.data.splits.dataset_window_ends`), also when
the window reaches into the previous press; for a rest-referenced model also a rest
image before them (:func:`beadsight.data.rest.rest_ends`), as in training. ``coverage``
is their share of the split's valid frames: frames without a rest image count as not
covered.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.data.dataset import Dataset
from beadsight.data.rest import REST_SETTLE_FRAMES
from beadsight.data.splits import (
    DEFAULT_FRACTIONS,
    SPLITS,
    dataset_window_ends,
    split_presses,
    valid_frames,
)
from beadsight.evaluation.config import SPLIT_CHOICES, EvaluationError

log = logging.getLogger(__name__)

REFERENCE_SPLIT_SOURCE = "reference checkpoint test_indices"
GIVEN_SPLIT, GIVEN_SOURCE = "held-out", "given"  # presses chosen by the caller


@dataclass(frozen=True)
class SplitSelection:
    """Which presses (or frames) are evaluated, and which are the training ones (baselines).

    frames / train_frames: the window-end frames a reference checkpoint stored
    (None: every frame of the presses that ends a full window).
    """

    name: str  # "test", "val" or "all"
    press_ids: np.ndarray  # (K,) int64 sorted
    train_ids: np.ndarray  # (J,) int64 sorted
    source: str  # "checkpoint", "recomputed", "all" or REFERENCE_SPLIT_SOURCE
    frames: np.ndarray | None = None  # (M,) int64 sorted
    train_frames: np.ndarray | None = None


def _stored_split(training: dict, ds: Dataset) -> tuple[dict[str, np.ndarray] | None, str]:
    """The checkpoint's stored press ids if they fit ``ds``; else (None, why not).

    ``training`` is ``meta.training`` as the training run writes it: ``split``
    ({"train", "val", "test"} press ids), ``dataset_fingerprint``
    (:func:`beadsight.data.dataset.dataset_fingerprint`), ``split_fractions``,
    ``split_seed``. A stored ``num_presses`` (inside ``split``) is checked too.
    """
    stored = training.get("split")
    if not isinstance(stored, dict):
        return None, "the checkpoint stores no press split (meta.training['split'])"
    try:
        ids = {k: np.sort(np.asarray(stored[k], dtype=np.int64).reshape(-1)) for k in SPLITS}
    except (KeyError, TypeError, ValueError) as e:
        return None, f"the checkpoint's stored split is malformed ({e!r})"
    stored_n = stored.get("num_presses")
    if stored_n is not None and int(stored_n) != ds.num_presses:
        return None, f"it was made for {stored_n} presses, the dataset has {ds.num_presses}"
    largest = max((int(v.max()) for v in ids.values() if v.size), default=-1)
    if largest >= ds.num_presses:
        return None, f"it names press {largest}, the dataset has {ds.num_presses} presses"
    stored_fp = training.get("dataset_fingerprint", stored.get("dataset_fingerprint"))
    if stored_fp is not None:
        from beadsight.data.dataset import dataset_fingerprint

        ours = dataset_fingerprint(ds)
        if ours != stored_fp:
            trained_on = training.get("dataset_path", "another dataset")
            return None, (
                f"it was made for {trained_on} (dataset_fingerprint {stored_fp}), and "
                f"{ds.path} has fingerprint {ours}"
            )
    return ids, ""


def _split_params(training: dict) -> tuple[tuple[float, float, float], int]:
    """The training run's split fractions and seed (defaults: 70/10/20, seed 0)."""
    stored = training.get("split") if isinstance(training.get("split"), dict) else {}
    config = training.get("config") if isinstance(training.get("config"), dict) else {}
    fractions = (
        training.get("split_fractions")
        or stored.get("fractions")
        or config.get("split")
        or DEFAULT_FRACTIONS
    )
    seed = training.get("split_seed", stored.get("seed", config.get("seed", 0)))
    return tuple(float(f) for f in fractions), int(seed)  # type: ignore[return-value]


def select_split(model: PressureModel, ds: Dataset, split: str) -> SplitSelection:
    """Presses (or frames) to evaluate for ``split`` ("test", "val" or "all"); module doc."""
    if split not in SPLIT_CHOICES:
        raise EvaluationError(f"--split {split!r}: expected one of {SPLIT_CHOICES}")
    everything = np.arange(ds.num_presses, dtype=np.int64)
    if split == "all":
        return SplitSelection("all", everything, everything, "all")
    if model.meta.provenance.get("source") == "reference":
        return _reference_split(model, ds, split)
    ids, why = _stored_split(model.meta.training, ds)
    source = "checkpoint"
    if ids is None:
        fractions, seed = _split_params(model.meta.training)
        try:
            ids = split_presses(ds.num_presses, fractions, seed)
        except ValueError as e:
            raise EvaluationError(f"{model.source}: cannot recompute the split: {e}") from None
        source = "recomputed"
        log.warning(
            "not using the checkpoint's %s split: %s; recomputed it with split_presses(%d, "
            "fractions=%s, seed=%d)",
            split,
            why,
            ds.num_presses,
            fractions,
            seed,
        )
    return SplitSelection(split, ids[split], ids["train"], source)


def given_presses(
    ds: Dataset, presses, train_presses=None, name: str = GIVEN_SPLIT
) -> SplitSelection:
    """A selection of the press ids ``presses`` (and ``train_presses`` for the baselines),
    e.g. a calibration's held-out presses scored with a model trained elsewhere."""
    ids = np.unique(np.asarray(presses, dtype=np.int64).reshape(-1))
    train = np.unique(np.asarray([] if train_presses is None else train_presses, np.int64))
    bad = np.concatenate([ids, train])
    bad = bad[(bad < 0) | (bad >= ds.num_presses)]
    if bad.size:
        raise EvaluationError(
            f"press {int(bad[0])} is not a press of {ds.path} ({ds.num_presses} presses)"
        )
    return SplitSelection(name, ids, train, GIVEN_SOURCE)


def _indices(training: dict, key: str) -> np.ndarray | None:
    """Sorted unique frame indices stored under ``key``; None if absent or not integers."""
    value = training.get(key)
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    if not np.isfinite(arr).all() or not np.array_equal(arr, np.round(arr)):
        return None
    return np.unique(arr.astype(np.int64))


def _reference_split(model: PressureModel, ds: Dataset, split: str) -> SplitSelection:
    """The reference checkpoint's own test frames, if ``ds`` is the file they index."""
    training = model.meta.training
    refuse = f"--split {split} refused for the reference checkpoint {model.source} on {ds.path}: "
    if split == "val":
        raise EvaluationError(
            refuse + "the reference stores no validation split (only train_indices and "
            "test_indices); use --split test, or --split all (which includes its training frames)"
        )
    test, train = _indices(training, "test_indices"), _indices(training, "train_indices")
    if test is None or train is None or test.size == 0:
        raise EvaluationError(
            refuse + "it stores no usable train_indices/test_indices, so the frames it was "
            "trained on are unknown; use --split all (which includes its training frames)"
        )
    why = _reference_mismatch(training, ds, np.concatenate([train, test]))
    if why:
        raise EvaluationError(
            refuse + f"{why}. Its test_indices only mean something in the file it was trained "
            "on; pass that file, or use --split all (which includes its training frames)"
        )
    log.info(
        "using the reference checkpoint's test_indices: %d test frames (%d training frames) "
        "of %s, which is the file they index",
        test.size,
        train.size,
        ds.path,
    )
    press_ids = np.unique(ds.press_id[test][ds.press_id[test] >= 0]).astype(np.int64)
    train_ids = np.unique(ds.press_id[train][ds.press_id[train] >= 0]).astype(np.int64)
    return SplitSelection("test", press_ids, train_ids, REFERENCE_SPLIT_SOURCE, test, train)


def _reference_mismatch(training: dict, ds: Dataset, indices: np.ndarray) -> str:
    """Why ``ds`` is not the file the reference indices were made for ('' if it is)."""
    trained_on = str(training.get("dataset_path") or "")
    if trained_on and Path(trained_on).name != ds.path.name:
        return f"its indices are frames of {trained_on}, not of {ds.path.name}"
    if indices.min() < 0 or indices.max() >= len(ds):
        return (
            f"its indices reach frame {int(indices.max())}, and {ds.path} has {len(ds)} "
            "frames: not the file they index"
        )
    invalid = indices[~ds.valid[indices]]
    if invalid.size:
        return (
            f"its frame {int(invalid[0])} (and {invalid.size - 1} more) is not a valid frame "
            f"of {ds.path}: not the file they index"
        )
    return ""


def evaluation_frames(
    model: PressureModel, ds: Dataset, selection: SplitSelection, max_frames: int | None
) -> np.ndarray:
    """(M,) sorted dataset indices of the frames to evaluate (window ends of the split).

    With ``max_frames``, that many frames evenly spaced over the whole split (a
    quick estimate of the full evaluation that still covers every press).
    """
    if selection.press_ids.size == 0 and selection.frames is None:
        raise EvaluationError(
            f"{ds.path}: the {selection.name!r} split has no presses ({ds.num_presses} in the "
            "dataset); use --split all"
        )
    ends = selection_ends(ds, selection, model.span, train=False, rest=bool(model.rest))
    if ends.size == 0:
        rest = (
            f" and a rest image before them (a run of {REST_SETTLE_FRAMES} valid unloaded frames)"
            if model.rest
            else ""
        )
        raise EvaluationError(
            f"window mismatch: the checkpoint {model.source} needs {model.span} "
            f"consecutive valid frames of history{rest}, but no frame of the {selection.name!r} "
            f"split of {ds.path} has them (longest run of valid frames: "
            f"{_longest_valid_run(ds)})"
        )
    if max_frames is not None and ends.size > max_frames:
        ends = ends[subsample(ends.size, max_frames)]
    return ends


def selection_ends(
    ds: Dataset, selection: SplitSelection, span: int, train: bool, rest: bool = False
) -> np.ndarray:
    """The window-end frames of the split (``train``: of its training part); ``rest``: only
    those with a rest image before them (a rest-referenced model's)."""
    frames = selection.train_frames if train else selection.frames
    ids = selection.train_ids if train else selection.press_ids
    if frames is None:
        return dataset_window_ends(ds, span, ids, rest=rest)
    return np.intersect1d(frames, dataset_window_ends(ds, span, rest=rest)).astype(np.int64)


def coverage(
    ds: Dataset, selection: SplitSelection, span: int, evaluated: int, rest: bool = False
) -> dict:
    """``coverage``: frames evaluated / valid frames of the split; ``window_coverage``:
    frames with a full window of real history (and, with ``rest``, a rest image before
    them) / valid frames (the same unless ``--max-frames`` took an even sample of them);
    and ``valid_frames``."""
    if selection.frames is not None:
        candidates = int(ds.valid[selection.frames].sum())
    else:
        candidates = int(valid_frames(ds, selection.press_ids).size)
    windowed = int(selection_ends(ds, selection, span, train=False, rest=rest).size)
    return {
        "coverage": evaluated / candidates if candidates else 0.0,
        "window_coverage": windowed / candidates if candidates else 0.0,
        "valid_frames": candidates,
    }


def _longest_valid_run(ds: Dataset) -> int:
    best = count = 0
    for good in ds.valid.tolist():
        count = count + 1 if good else 0
        best = max(best, count)
    return best


def subsample(n: int, k: int) -> np.ndarray:
    """``k <= n`` evenly spaced sorted indices into ``range(n)``, first and last included."""
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64))
