"""Dataset commands: ``beadsight info`` (datasets and checkpoints) and
``beadsight import-reference``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(commands) -> None:
    commands.add(
        "info",
        help="summarise a dataset or a checkpoint (ours or the reference's)",
        arguments=_info_arguments,
        run=_info,
    )
    commands.add(
        "import-reference",
        help="convert a reference processed HDF5 file to this project's format",
        description="Reference files are also accepted directly by train, evaluate and predict; "
        "importing stores RGB frames, newtons, float64 timestamps and press segmentation.",
        arguments=_import_arguments,
        run=_import,
    )


def _info_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="dataset .h5 file or checkpoint .pt file")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _import_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="reference .hdf5 file")
    p.add_argument("--out", required=True, help="output dataset .h5")


def dataset_summary(path: str) -> dict:
    from beadsight.data.dataset import open_dataset

    with open_dataset(path) as ds:
        contact = ds.force_n[ds.contact]
        return {
            "path": str(ds.path),
            "format": "reference" if ds.is_reference else "beadsight",
            "frames": len(ds),
            "valid_frames": int(ds.valid.sum()),
            "presses": ds.num_presses,
            "image_size_px": ds.image_size,
            "channel_order": ds.channel_order,
            "fps": ds.fps,
            "duration_s": float(ds.timestamp_s[-1] - ds.timestamp_s[0]) if len(ds) else 0.0,
            "peak_force_n": float(contact.max()) if len(contact) else 0.0,
            "mean_contact_force_n": float(contact.mean()) if len(contact) else 0.0,
            "geometry": ds.geometry.to_dict(),
        }


def _info(args: argparse.Namespace) -> int:
    import h5py

    from beadsight.checkpoint import checkpoint_summary, looks_like_checkpoint
    from beadsight.errors import BeadSightError

    path = Path(args.file)
    if path.is_file() and not h5py.is_hdf5(path):  # every file load_checkpoint may read
        if not looks_like_checkpoint(path):
            raise BeadSightError(
                f"{path}: neither a dataset (an HDF5 file) nor a checkpoint (a torch zip "
                "archive or pickle)"
            )
        summary = checkpoint_summary(path)
    else:  # a dataset, or a missing path, directory or device: open_dataset names it
        summary = dataset_summary(args.file)
    if args.json:
        print(json.dumps(summary))
        return 0
    for key, value in summary.items():
        print(f"{key:>22}: {value}")
    return 0


def _import(args: argparse.Namespace) -> int:
    from beadsight.data.dataset import import_reference

    out = import_reference(args.source, args.out)
    print(f"wrote {out}")
    return 0
