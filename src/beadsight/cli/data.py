"""Dataset commands: ``beadsight info`` (datasets and checkpoints),
``beadsight import-reference`` and ``beadsight export-dataset``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(commands) -> None:
    commands.add("info", _info, _info_arguments)
    commands.add("import-reference", _import, _import_arguments)
    commands.add("export-dataset", _export, _export_arguments)


def _info_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="dataset .h5 file or checkpoint .pt file")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _import_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="reference .hdf5 file")
    p.add_argument("--out", required=True, help="output dataset .h5")


def _export_arguments(p: argparse.ArgumentParser) -> None:
    from beadsight.data.reference_file import EXPORT_FORMATS

    p.add_argument("data", help="dataset .h5 (this project's format)")
    p.add_argument(
        "--format",
        choices=EXPORT_FORMATS,
        default="reference",
        help="reference: the original BeadSight code's processed HDF5 layout (BGR frames, "
        "grams, float32 columns; docs/data_format.md) (default: reference)",
    )
    p.add_argument("--out", required=True, help="output .h5 file")
    p.add_argument(
        "--compression-level", type=int, default=0, help="gzip level of the images, 0 = none"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")


def dataset_summary(path: str) -> dict:
    from beadsight.data.dataset import open_dataset
    from beadsight.data.timing import duration

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
            **duration(ds),
            "peak_force_n": float(contact.max()) if len(contact) else 0.0,
            "mean_contact_force_n": float(contact.mean()) if len(contact) else 0.0,
            "geometry": ds.geometry.to_dict(),
        }


def _info(args: argparse.Namespace) -> int:
    """Summarise a dataset or a checkpoint (ours or the reference's)."""
    import h5py

    from beadsight.errors import BeadSightError

    path = Path(args.file)
    if path.is_file() and not h5py.is_hdf5(path):  # every file load_checkpoint may read
        # here, not above: a dataset's summary needs no torch (3 s to import)
        from beadsight.checkpoint import checkpoint_summary, looks_like_checkpoint

        if not looks_like_checkpoint(path):
            raise BeadSightError(
                f"{path}: neither a dataset (an HDF5 file) nor a checkpoint (a torch zip "
                "archive or pickle)"
            )
        summary = checkpoint_summary(path)
    else:  # a dataset, or a missing path, directory or device: open_dataset names it
        summary = dataset_summary(args.file)
    warning = summary.pop("warning", None)  # None: all is well, nothing to say
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print(json.dumps({**summary, **({"warning": warning} if warning else {})}))
        return 0
    for key, value in summary.items():
        print(f"{key:>22}: {value}")
    return 0


def _import(args: argparse.Namespace) -> int:
    """Convert a reference processed HDF5 file to this project's format.

    Reference files are also accepted directly by train, evaluate and predict; importing
    stores RGB frames, newtons, float64 timestamps and press segmentation.
    """
    from beadsight.data.reference_file import import_reference

    out = import_reference(args.source, args.out)
    print(f"wrote {out}")
    return 0


def _export(args: argparse.Namespace) -> int:
    """Write a dataset in the reference's processed HDF5 layout.

    Write DATA with the names, dtypes, units (grams), BGR frames and attributes of the
    reference's raw_data_process.py, for the reference's own scripts.
    """
    from beadsight.data.reference_file import export_reference

    out = export_reference(
        args.data, args.out, compression_level=args.compression_level, overwrite=args.overwrite
    )
    print(f"wrote {out} ({args.format} layout)")
    return 0
