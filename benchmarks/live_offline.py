"""Offline and live on the same presses: the paper's metrics of ``evaluate`` and of a live
replay of the same dataset, and where they differ.

    PYTHONPATH=src .venv/bin/python benchmarks/live_offline.py DATA.h5 [--checkpoint C] [--json]
        [--work DIR] [--backend B]

1. offline: ``beadsight evaluate --checkpoint C --data DATA.h5 --split all --resize``
   (``--resize``: a no-op when the sizes agree; the replay resizes frames the same way);
2. live: ``beadsight live --checkpoint C --source DATA.h5 --no-viewer --output rec.h5``,
   default settings otherwise: the file played once at its fps, as a camera;
3. the live readings scored with the project's metrics (:mod:`beadsight.metrics`) against
   the file's truth (:func:`beadsight.data.labels.label_maps`) at each reading's
   ``frame_index`` (the dataset row), on the frames ``evaluate`` could score: valid frames
   of a press.

Rows (each: mae_kpa, force_error_pct, cop_error_mm, iou, worst_region_mae_kpa, frames,
coverage = frames scored / the file's valid frames of presses): ``offline``; ``live``
(every scorable reading); ``live_on_offline_frames`` (the readings at frames ``evaluate``
scored) and ``offline_on_live_frames`` (``evaluate``'s predictions at those same frames),
so the gap splits into *which frames* got a reading and *what* the reading was.

``why`` counts the causes: valid frames with no reading (``before_first_reading``: the
window filling and the rest reference being taken at start-up; ``skipped``: the live loop
slower than the camera, frame_index gaps); readings at frames ``evaluate`` does not score
(the row invalid or outside a press; a window over an invalid row or a capture gap; no
rest image before the frame for a rest-referenced model); readings whose frame came late
on the host (the replay fell behind its schedule by more than half a frame period, so the
predictor saw a capture gap the file does not have); and readings whose map differs from
``evaluate``'s at the same frame by more than the runtime parity tolerance
(:data:`beadsight.inference.parity.PARITY_TOLERANCE`: the window or the rest image was
not the offline one), split by whether a late frame preceded them within one window.
The last line is a JSON object (--json: the only line).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
from pathlib import Path

import h5py
import numpy as np

from beadsight.config import SensorGeometry
from beadsight.data.dataset import Dataset, open_dataset
from beadsight.data.labels import label_maps
from beadsight.data.rest import rest_ends
from beadsight.data.splits import dataset_window_ends, valid_frames
from beadsight.devices.replay import replay_times_s
from beadsight.inference.parity import PARITY_TOLERANCE
from beadsight.metrics import PAPER_METRIC_KEYS, MetricsAccumulator

BATCH = 64  # maps scored at once
LATE_PERIODS = 0.5  # a frame this many periods behind the replay's schedule came late


def run(argv: list[str]) -> None:
    """``beadsight ARGV`` in this process (torch is imported once for both commands);
    SystemExit with what it printed if it fails."""
    from beadsight.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    if code != 0:
        raise SystemExit(f"beadsight {' '.join(argv)} failed:\n{out.getvalue()}{err.getvalue()}")


def row(result: dict, valid: int) -> dict:
    """The paper's metrics of an accumulator's ``result`` with frames and coverage."""
    out = {key: result[key] for key in PAPER_METRIC_KEYS}
    out["frames"] = result["frames"]
    out["coverage"] = round(result["frames"] / valid, 4) if valid else None
    return out


def score(
    ds: Dataset, geometry: SensorGeometry, frames: np.ndarray, maps, picks: np.ndarray
) -> dict:
    """Metrics of ``maps[picks[k]]`` (kPa) against the truth at dataset rows ``frames[k]``."""
    acc = MetricsAccumulator(geometry)
    for i in range(0, len(frames), BATCH):
        f, p = frames[i : i + BATCH], picks[i : i + BATCH]
        order = np.argsort(p)  # h5py reads rows in increasing order
        pred = np.empty((len(p), *maps.shape[1:]), np.float32)
        pred[order] = maps[p[order]]
        gt = label_maps(ds.force_n[f], ds.position_mm[f], ds.contact[f], geometry)
        acc.update(pred, gt, ds.position_mm[f])
    return acc.result()


def late_frames(ds: Dataset, frame_index: np.ndarray, timestamp_s: np.ndarray) -> np.ndarray:
    """(R,) bool: the reading's frame came later than the replay's schedule allows, beyond
    the latest lag seen before it (the replay never catches up, so each new lag is a new
    hold-up). The schedule: :func:`beadsight.devices.replay.replay_times_s`."""
    sched = replay_times_s(ds.timestamp_s, ds.fps, ds.fps)[frame_index]
    lag = timestamp_s - timestamp_s[0] - (sched - sched[0])
    before = np.maximum.accumulate(np.concatenate([[lag[0]], lag[:-1]]))
    return lag - before > LATE_PERIODS / ds.fps


def compare(ds: Dataset, model_rest: bool, span: int, rec: Path, pred_file: Path, metrics: dict):
    """The rows and the causes of the module docstring."""
    from beadsight.live.recording.readings import open_readings

    scorable = valid_frames(ds)
    with open_readings(rec) as rf, h5py.File(pred_file, "r") as pf:
        geometry = ds.geometry.with_image_size(rf.geometry.image_size_px)
        fi = rf.frame_index.astype(np.int64)
        off_index = pf["index"][()].astype(np.int64)
        inside = (fi >= 0) & (fi < len(ds))
        ok = inside & np.isin(fi, scorable)
        live = score(ds, geometry, fi[ok], rf.pressure_kpa, np.flatnonzero(ok))
        on_off = ok & np.isin(fi, off_index)
        live_on_off = score(ds, geometry, fi[on_off], rf.pressure_kpa, np.flatnonzero(on_off))
        off_pos = np.searchsorted(off_index, fi[on_off])
        off_on_live = score(ds, geometry, fi[on_off], pf["pred_kpa"], off_pos)
        late = late_frames(ds, fi, rf.timestamp_s)
        differs = np.zeros(len(fi), bool)
        for k, pos in zip(np.flatnonzero(on_off).tolist(), off_pos.tolist(), strict=True):
            offline = pf["pred_kpa"][pos]
            tol = PARITY_TOLERANCE.tolerance_kpa(float(offline.max()))
            differs[k] = float(np.abs(rf.pressure_kpa[k] - offline).max()) > tol
    valid = int(scorable.size)
    rows = {
        "offline": row(metrics, valid),
        "live": row(live, valid),
        "live_on_offline_frames": row(live_on_off, valid),
        "offline_on_live_frames": row(off_on_live, valid),
    }
    why = causes(ds, model_rest, span, fi, inside, ok, on_off, late, differs, scorable)
    return rows, why, rf.provenance.get("backend")


def causes(ds, model_rest, span, fi, inside, ok, on_off, late, differs, scorable) -> dict:
    """The counts of ``why`` (module docstring)."""
    no_reading = np.setdiff1d(scorable, fi[ok])
    first = int(fi[0]) if len(fi) else len(ds)
    windowed = dataset_window_ends(ds, span)
    f_in = fi[inside]
    not_offline = ok & ~on_off
    recent_late = np.zeros(len(fi), bool)  # a late frame within the reading's window
    for k in np.flatnonzero(late):
        recent_late |= (fi >= fi[k]) & (fi < fi[k] + span)
    return {
        "valid_frames": int(scorable.size),
        "readings": len(fi),
        "readings_outside_the_file": int((~inside).sum()),
        "valid_frames_without_reading": int(no_reading.size),
        "before_first_reading": int((no_reading < first).sum()),
        "skipped": int((no_reading > first).sum()),
        "frame_index_gaps": int((np.diff(fi) > 1).sum()),
        "readings_at_invalid_rows": int((~ds.valid[f_in]).sum()),
        "readings_outside_presses": int((ds.valid[f_in] & (ds.press_id[f_in] < 0)).sum()),
        "readings_offline_does_not_score": int(not_offline.sum()),
        "of_which_window_over_invalid_or_gap": int((not_offline & ~np.isin(fi, windowed)).sum()),
        "of_which_no_rest_image_offline": int(
            (not_offline & np.isin(fi, windowed) & (rest_ends(ds.force_n, ds.valid)[fi] < 0)).sum()
        )
        if model_rest
        else 0,
        "late_frame_readings": int(late.sum()),
        "compared_with_offline": int(on_off.sum()),
        "differ_from_offline": int(differs.sum()),
        "differ_after_a_late_frame": int((differs & recent_late).sum()),
        "differ_without_a_late_frame": int((differs & ~recent_late).sum()),
    }


def gap(rows: dict) -> dict:
    """live minus offline per metric: overall, and on the same frames."""

    def minus(a: dict, b: dict) -> dict:
        return {
            key: None if a[key] is None or b[key] is None else round(a[key] - b[key], 4)
            for key in (*PAPER_METRIC_KEYS, "coverage")
        }

    return {
        "live_minus_offline": minus(rows["live"], rows["offline"]),
        "same_frames_live_minus_offline": minus(
            rows["live_on_offline_frames"], rows["offline_on_live_frames"]
        ),
    }


def measure(data: Path, checkpoint: Path, work: Path, backend: str | None = None) -> dict:
    """Run both and compare (module docstring); files go to ``work``."""
    from beadsight.checkpoint import load_checkpoint

    offline = work / "offline"
    rec = work / "live.h5"
    common = ["--checkpoint", str(checkpoint)]
    if backend is not None:  # else each command's default: evaluate torch, live auto
        common += ["--backend", backend]
    run(
        ["evaluate", *common, "--data", str(data), "--split", "all", "--resize"]
        + ["--out", str(offline), "--overwrite", "--no-plots", "--no-progress"]
    )
    run(
        ["live", *common, "--source", str(data), "--no-viewer"]
        + ["--output", str(rec), "--overwrite"]
    )
    metrics = json.loads((offline / "metrics.json").read_text())
    model = load_checkpoint(checkpoint, "cpu")
    with open_dataset(data) as ds:
        rows, why, live_backend = compare(
            ds, bool(model.rest), model.span, rec, offline / "predictions.h5", metrics
        )
    return {
        "dataset": str(data),
        "checkpoint": str(checkpoint),
        "presses": metrics["presses"],
        "offline_backend": metrics["backend"],
        "live_backend": live_backend,
        "rows": rows,
        "gap": gap(rows),
        "why": why,
    }


def main(argv: list[str] | None = None) -> None:
    from beadsight.assets import shipped_model_path

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data", type=Path, help="dataset file (.h5) of presses with true forces")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped sim model")
    p.add_argument("--work", type=Path, default=None, help="keep the evaluation and recording here")
    p.add_argument(
        "--backend",
        default=None,
        help="the runtime both run (default: each command's own: evaluate torch, live auto)",
    )
    p.add_argument("--json", action="store_true", help="print only the JSON object")
    args = p.parse_args(argv)
    checkpoint = args.checkpoint or shipped_model_path()
    with tempfile.TemporaryDirectory(prefix="live_offline_") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        figures = measure(args.data, checkpoint, work, args.backend)
        if args.work is not None:
            figures["work"] = str(work)  # metrics.json, predictions.h5, the recording
    if not args.json:
        keys = (*PAPER_METRIC_KEYS, "frames", "coverage")
        print(f"{'':24s}" + "".join(f"{k[:14]:>15s}" for k in keys))
        for name, r in figures["rows"].items():
            print(f"{name:24s}" + "".join(f"{_text(r[k]):>15s}" for k in keys))
        for name, value in figures["why"].items():
            print(f"{name:40s} {value}")
    print(json.dumps(figures))


def _text(value) -> str:
    return "-" if value is None else f"{value:.4g}" if isinstance(value, float) else str(value)


if __name__ == "__main__":
    main()
