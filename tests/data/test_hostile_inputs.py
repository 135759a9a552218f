"""Issue 26: hostile raw recordings for ``process`` -- a named error, never a hang, an
unbounded read or a leftover ``.partial``."""

from __future__ import annotations

import os

import pytest
from helpers.recording import Timeline, write_beadsight_raw

from beadsight.cli import main
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.run import process_recording
from beadsight.data.recording import RecordingError
from beadsight.data.recording.text import MAX_LOG_BYTES, MAX_RECORD_CHARS

SMALL = ProcessConfig(image_size=64, preprocess="none")


@pytest.fixture
def raw(tmp_path):
    return write_beadsight_raw(tmp_path / "raw", Timeline(presses=2))


def test_a_bad_video_chunk_midway_leaves_no_partial(raw, tmp_path, capsys):
    chunk = sorted(raw.glob("video_*.avi"))[1]
    chunk.write_bytes(b"not a video" * 100)
    out = tmp_path / "d.h5"
    with pytest.raises(RecordingError, match=rf"{chunk}: cannot open video"):
        process_recording(raw, out, SMALL, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]  # no dataset, no .partial
    assert main(["process", str(raw), "--out", str(out), "--no-progress"]) == 1
    assert f"{chunk}: cannot open video" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]


# --- hangs and unbounded reads: never block on a FIFO, never read without bound ------------
def _process_err(raw, out, capsys) -> str:
    assert main(["process", str(raw), "--out", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "internal error" not in err
    return err


def test_a_fifo_as_force_log_is_refused_not_waited_on(raw, tmp_path, capsys):
    force = raw / "force.csv"
    force.unlink()
    os.mkfifo(force)  # nobody ever writes to it: reading it would block for ever
    err = _process_err(raw, tmp_path / "d.h5", capsys)
    assert f"{force}: is not a regular file (a FIFO or device); expected a text log" in err


def test_a_fifo_as_a_video_chunk_is_refused_not_waited_on(raw, tmp_path, capsys):
    chunk = sorted(raw.glob("video_*.avi"))[2]
    chunk.unlink()
    os.mkfifo(chunk)
    err = _process_err(raw, tmp_path / "d.h5", capsys)
    assert f"{chunk}: is not a regular file (a FIFO or device); expected a video file" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]


def test_a_force_log_pointing_at_dev_zero_is_refused(raw, tmp_path, capsys):
    force = raw / "force.csv"
    force.unlink()
    force.symlink_to("/dev/zero")
    err = _process_err(raw, tmp_path / "d.h5", capsys)
    assert f"{force}: is not a regular file (a FIFO or device); expected a text log" in err


def test_a_log_over_the_size_bound_is_refused_before_reading(raw, tmp_path, capsys):
    force = raw / "force.csv"
    with open(force, "r+b") as f:
        f.truncate(MAX_LOG_BYTES + 1)  # sparse: no disk used, nothing read
    err = _process_err(raw, tmp_path / "d.h5", capsys)
    assert f"{force}: {MAX_LOG_BYTES + 1} bytes, more than {MAX_LOG_BYTES} for a text log" in err


def test_one_endless_line_is_refused(raw, tmp_path, capsys):
    force = raw / "force.csv"
    lines = force.read_text().split("\n")
    lines[5] = "1" * (MAX_RECORD_CHARS + 1)
    force.write_text("\n".join(lines))
    err = _process_err(raw, tmp_path / "d.h5", capsys)
    assert f"{force} line 6: {MAX_RECORD_CHARS + 1} characters, more than" in err


# --- validation gaps: printer positions -----------------------------------------------------
def _set_printer_field(raw, line: int, col: int, value: str) -> None:
    path = raw / "printer.csv"
    rows = path.read_text().split("\n")
    parts = rows[line - 1].split(",")
    parts[col] = value
    rows[line - 1] = ",".join(parts)
    path.write_text("\n".join(rows))


@pytest.mark.parametrize(
    ("value", "what"),
    [("1e308", r"is absurd \(beyond 1000 mm\)"), ("nan", "is missing at a press")],
)
def test_absurd_or_missing_printer_position_is_a_named_error(raw, tmp_path, value, what):
    line = next(  # the first move to a press location
        k + 1
        for k, row in enumerate((raw / "printer.csv").read_text().split("\n"))
        if row.split(",")[-1:] == ["0"] and ",G1 X" in row
    )
    _set_printer_field(raw, line, 3, value)
    with pytest.raises(
        RecordingError, match=rf"printer\.csv line {line}: printer position .*{what}"
    ):
        process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]


def test_a_lens_calibration_with_focal_length_zero_is_refused(raw, tmp_path, capsys):
    """fx = 0 mapped every pixel to one point: every frame one colour, exit 0."""
    lens = tmp_path / "lens.json"
    lens.write_text(
        '{"format": "beadsight-fisheye-calibration", "K": [[0, 0, 60], [0, 0, 48], [0, 0, 1]], '
        '"D": [0, 0, 0, 0], "image_hw": [96, 120]}'
    )
    out = tmp_path / "d.h5"
    assert (
        main(["process", str(raw), "--out", str(out), "--preprocess", str(lens), "--no-progress"])
        == 1
    )
    err = capsys.readouterr().err
    assert f"{lens}: K's focal lengths fx, fy must be > 0 px, got 0, 0" in err
    assert not out.exists()
