"""Issue 13 item 14 for the dataset writers: a full disk (a real 256 KiB tmpfs) is a named
error and a non-zero exit, and a damaged file never gets its final name."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from helpers.recording import Timeline, write_beadsight_raw

from beadsight.cli import main
from beadsight.config import SensorGeometry
from beadsight.data.dataset import open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.run import process_recording
from beadsight.files import WriteError


def _leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_dataset_writer_on_a_full_disk(full_disk):
    out = full_disk / "d.h5"
    rng = np.random.default_rng(0)
    w = DatasetWriter(out, SensorGeometry(image_size_px=64))
    w.space_margin_bytes = 64 * 1024  # let a few frames in before the 256 KiB disk is "full"
    written = 0
    with pytest.raises(WriteError, match=r"d\.h5\.partial: disk full .*d\.h5 was not written"):
        for k in range(100):  # 12 KB of noise per frame
            frames = rng.integers(0, 256, (1, 64, 64, 3), dtype=np.uint8)
            w.append(frames, [1.0], [[0.0, 0.0]], [True], [1.7e9 + k / 30])
            written += 1
    assert written >= 3
    with pytest.raises(WriteError, match="was not written"):
        w.close()  # never renamed into place
    with pytest.raises(WriteError, match="earlier write failed"):
        w.append(frames, [1.0], [[0.0, 0.0]], [True], [0.0])
    assert _leftovers(full_disk) == ["d.h5.partial"]
    with h5py.File(full_disk / "d.h5.partial", "r") as f:  # intact: what was written is there
        assert f["frames"].shape == (written, 64, 64, 3) and f["force"].shape == (written,)


def test_simulate_on_a_full_disk_exits_non_zero(full_disk, capsys):
    out = full_disk / "sim.h5"
    code = main(
        ["simulate", "--out", str(out), "--presses", "3", "--image-size", "64", "--no-progress"]
    )
    assert code == 1
    err = capsys.readouterr().err
    # the expected size is checked against the free space before anything is written
    assert "sim.h5: the dataset needs about" in err and "GB free" in err
    assert "Traceback" not in err and _leftovers(full_disk) == []


def test_process_on_a_full_disk_exits_non_zero(full_disk, tmp_path, capsys):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=2), frame_hw=(128, 160))
    out = full_disk / "d.h5"
    config = ProcessConfig(image_size=128, preprocess="none", workers=2)
    with pytest.raises(WriteError, match=r"d\.h5\.partial: disk full"):
        process_recording(raw, out, config, progress=False)
    assert _leftovers(full_disk) == ["d.h5.partial"]
    (full_disk / "d.h5.partial").unlink()
    code = main(
        [
            "process",
            str(raw),
            "--out",
            str(out),
            "--image-size",
            "128",
            "--preprocess",
            "none",
            "--no-progress",
        ]
    )
    assert code == 1
    assert "d.h5.partial: disk full" in capsys.readouterr().err
    assert not out.exists() and not (full_disk / "d.h5.qa.json").exists()


def test_a_finished_dataset_reads_back(tmp_path):
    """The rename happens once everything is written (and only then)."""
    out = tmp_path / "d.h5"
    with DatasetWriter(out, SensorGeometry(image_size_px=16)) as w:
        w.append(
            np.zeros((3, 16, 16, 3), np.uint8), [0, 1, 0], np.zeros((3, 2)), [1, 1, 1], [0, 1, 2]
        )
        assert not out.exists() and w.partial.exists()
    assert _leftovers(tmp_path) == ["d.h5"]
    with open_dataset(out) as ds:
        assert len(ds) == 3
