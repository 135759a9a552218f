"""The run folder on a full disk, and temporary files a killed run left behind."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight import load_checkpoint
from beadsight.cli import main
from beadsight.files import WriteError
from beadsight.train.config import TrainConfig
from beadsight.train.trainer import train

# width 1: checkpoints of ~80 KB (last.pt) and ~25 KB (best.pt) fit the 256 KiB test disk
SMALL = ["--width", "1", "--batch-size", "4", "--no-progress", "--device", "cpu"]


def _fill(disk: Path, leave_bytes: int) -> None:
    """Fill ``disk`` until at most ``leave_bytes`` are free."""
    stat = os.statvfs(disk)
    free = stat.f_bavail * stat.f_frsize
    with open(disk / "filler.bin", "wb") as f:
        f.write(b"\0" * max(0, free - leave_bytes))


def _temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_full_disk_at_the_first_checkpoint_is_a_named_one_line_error(
    make_dataset, full_disk, capsys
):
    data = make_dataset()
    run = full_disk / "run"
    # width 8: last.pt (~1.5 MB) overflows the disk inside torch's zip writer
    code = main(
        ["train", "--data", str(data), "--out", str(run), "--steps", "2", *SMALL, "--width", "8"]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert err[-1] == f"beadsight train: error: could not write {run / 'last.pt'}: disk full"
    assert not any("Traceback" in line for line in err)
    assert not (run / "last.pt").exists() and not (run / "best.pt").exists()
    assert _temps(run) == []


def test_full_disk_keeps_the_previous_checkpoint_intact(make_dataset, full_disk, capsys):
    data = make_dataset()
    run = full_disk / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "2", *SMALL]) == 0
    before = (run / "last.pt").read_bytes()
    _fill(full_disk, 20_000)
    code = main(
        ["train", "--data", str(data), "--out", str(run), "--steps", "4", "--resume", *SMALL]
    )
    assert code == 1
    err = capsys.readouterr().err
    assert f"could not write {run / 'last.pt'}: disk full" in err
    assert (run / "last.pt").read_bytes() == before  # never a damaged file under the name
    assert load_checkpoint(run / "last.pt").meta.training["step"] == 2
    assert _temps(run) == []


def test_write_error_from_the_library_names_the_file(make_dataset, full_disk):
    data = make_dataset()
    _fill(full_disk, 40_000)
    config = TrainConfig(
        data=str(data),
        out=str(full_disk / "run"),
        width=1,
        batch_size=4,
        steps=2,
        progress=False,
        device="cpu",
    )
    with pytest.raises(WriteError, match=r"last\.pt: disk full"):
        train(config)


def test_resume_removes_temporary_files_a_killed_run_left(make_dataset, tmp_path, capsys):
    data = make_dataset()
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "2", *SMALL]) == 0
    stale = [".last.pt.k1l2m3.tmp", ".best.pt.a8b9c0.tmp", ".config.json.x1y2z3.tmp"]
    for name in stale:
        (run / name).write_bytes(b"half a checkpoint")
    (run / "notes.tmp").write_text("not ours")  # not a temporary file of a run file
    assert (
        main(["train", "--data", str(data), "--out", str(run), "--steps", "3", "--resume", *SMALL])
        == 0
    )
    assert _temps(run) == ["notes.tmp"]
    assert load_checkpoint(run / "last.pt").meta.training["step"] == 3
