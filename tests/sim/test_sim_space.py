"""Issue 26: `simulate` compresses by default, says the expected size, and refuses to
start on a disk without room for it."""

from __future__ import annotations

import h5py

from beadsight.cli import main


def test_simulate_refuses_a_disk_too_small_for_the_dataset(full_disk, capsys):
    out = full_disk / "sim.h5"
    code = main(["simulate", "--out", str(out), "--presses", "20", "--seed", "1", "--no-progress"])
    assert code == 1
    err = capsys.readouterr().err
    assert f"{out}: the dataset needs about " in err and "compression gzip" in err
    assert "GB free; free space, or simulate fewer presses" in err
    assert list(full_disk.iterdir()) == []  # refused before anything was written


def test_simulate_compresses_by_default_and_says_the_size(tmp_path, caplog):
    out = tmp_path / "sim.h5"
    argv = ["simulate", "--out", str(out), "--presses", "1", "--seed", "1", "--image-size", "64"]
    with caplog.at_level("INFO"):
        assert main([*argv, "--no-progress"]) == 0
    assert any("GB" in r.getMessage() and "about" in r.getMessage() for r in caplog.records)
    with h5py.File(out) as f:
        assert f["frames"].compression == "gzip"
