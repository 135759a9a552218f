"""Issue 13 items 1-3: raw logs of the reference rig, and implausible or hostile raw logs.

The force values with the counter are what the published sketch prints (grams + 10000*i,
i = 0..9 line by line); the printer log holds genuine command-block records (\\r-ended,
several \\n-separated G-code lines each).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.recording import (
    T0_UNIX,
    Timeline,
    write_beadsight_raw,
    write_reference_raw,
)

from beadsight.cli import main
from beadsight.data.dataset import open_dataset
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.run import process_recording
from beadsight.data.recording import RecordingError, open_recording
from beadsight.files import OutputExistsError

SMALL = ProcessConfig(image_size=32, workers=2, batch_frames=16)


def _truth_force(tl: Timeline, ds) -> np.ndarray:
    return tl.force_n(ds.timestamp_s - T0_UNIX)


# --- item 1: the force counter ----------------------------------------------------------
def test_force_counter_is_detected_decoded_and_reported(tmp_path, caplog):
    tl = Timeline(presses=2)
    raw = write_reference_raw(tmp_path / "ref", tl, counter=True)
    assert max(float(v.split(",")[1]) for v in (raw / "force_log.txt").read_text().split()) > 9e4
    with caplog.at_level("INFO"):
        qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    counter = qa["force_counter"]
    assert counter["detected"] and counter["decoded"] and counter["mode"] == "auto"
    assert counter["cycle_fraction"] == 1.0 and counter["lines_lost"] == 0
    assert "force_log.txt: decoded the reference sketch's +10000*i force counter" in caplog.text
    saved = json.loads((tmp_path / "d.h5.qa.json").read_text())
    assert saved["force_counter"]["decoded"] is True
    with open_dataset(tmp_path / "d.h5") as ds:
        valid = ds.valid
        np.testing.assert_allclose(ds.force_n[valid], _truth_force(tl, ds)[valid], atol=0.35)
        assert ds.force_n[valid].max() < 10  # true peak 9 N (not ~900 N)
        assert ds.num_presses == 2 and ds.contact.mean() < 0.5  # not every frame in contact
    assert qa["force_n"]["max"] == pytest.approx(9.0, abs=0.1)


def test_force_counter_forced_on_and_off(tmp_path, capsys):
    tl = Timeline(presses=2)
    plain = write_reference_raw(tmp_path / "plain", tl)
    coded = write_reference_raw(tmp_path / "coded", tl, counter=True)
    off = ProcessConfig(image_size=32, workers=2, force_counter="off", scale_capacity_n=2000.0)
    qa = process_recording(coded, tmp_path / "off.h5", off, progress=False)
    assert qa["force_counter"]["detected"] and not qa["force_counter"]["decoded"]
    assert any("--force-counter off keeps them" in w for w in qa["warnings"])
    assert qa["force_n"]["max"] > 800  # taken as they are, as asked (and said)
    on = ProcessConfig(image_size=32, workers=2, force_counter="on")
    qa = process_recording(plain, tmp_path / "on.h5", on, progress=False)
    assert qa["force_counter"]["decoded"] and not qa["force_counter"]["detected"]
    assert qa["force_n"]["max"] == pytest.approx(9.0, abs=0.1)  # a plain log decodes to itself
    code = main(
        [
            "process",
            str(coded),
            "--out",
            str(tmp_path / "cli.h5"),
            "--image-size",
            "32",
            "--force-counter",
            "auto",
            "--no-progress",
        ]
    )
    assert code == 0
    assert "decoded the reference sketch's +10000*i force counter" in capsys.readouterr().out


# --- item 3: multi-line command blocks ------------------------------------------------------
def test_printer_log_command_blocks_keep_every_gcode_line(tmp_path):
    tl = Timeline(presses=3)
    raw = write_reference_raw(tmp_path / "ref", tl, command_blocks=True)
    text = (raw / "printer_log.txt").read_bytes().decode()
    assert text.count("\r") == 3 + 3 and "\n" in text  # 3 non-data records + 3 press blocks
    rec = open_recording(raw)
    assert not any("malformed" in w for w in rec.warnings), rec.warnings
    presses = [g for g, d in zip(rec.moves.gcode, rec.moves.is_data, strict=True) if d]
    assert len(presses) == 3
    for block in presses:
        lines = block.split("\n")
        assert len(lines) == 3 and lines[0].startswith("G1 X") and lines[1] == "G1 Z127.5 F200"
    assert rec.moves.line.tolist() == [1, 2, 3, 4, 5, 6]
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    assert qa["presses"] == 3 and not any("malformed" in w for w in qa["warnings"])
    with open_dataset(tmp_path / "d.h5") as ds:
        times = ds.timestamp_s - T0_UNIX
        truth, _ = tl.position_at(times)
        np.testing.assert_allclose(ds.position_mm[ds.valid], truth[ds.valid], atol=1e-9)


# --- item 2: plausibility -------------------------------------------------------------------
def _replace_field(path, line: int, col: int, value: str) -> None:
    rows = path.read_text().split("\n")
    parts = rows[line - 1].split(",")
    parts[col] = value
    rows[line - 1] = ",".join(parts)
    path.write_text("\n".join(rows))


@pytest.mark.parametrize(("name", "col"), [("frames.csv", 2), ("force.csv", 2), ("force.csv", 0)])
def test_absurd_value_is_a_named_error_before_any_output(tmp_path, name, col):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=1))
    _replace_field(raw / name, 12, col, "1e308")
    out = tmp_path / "d.h5"
    with pytest.raises(RecordingError, match=rf"{name} line 12: .* is absurd"):
        process_recording(raw, out, SMALL, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]  # no dataset, no .partial
    code = main(["process", str(raw), "--out", str(out), "--no-progress"])
    assert code == 1 and not out.exists()


def test_absurd_grams_in_a_reference_force_log(tmp_path):
    raw = write_reference_raw(tmp_path / "ref", Timeline(presses=1))
    _replace_field(raw / "force_log.txt", 7, 1, "1e300")
    with pytest.raises(RecordingError, match=r"force_log\.txt line 7: force reading 1e\+300 g"):
        process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    assert not (tmp_path / "d.h5").exists()


def test_non_finite_readings_are_reported_with_their_lines(tmp_path):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=1))
    _replace_field(raw / "force.csv", 5, 2, "nan")
    _replace_field(raw / "force.csv", 9, 2, "inf")
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    text = "\n".join(qa["warnings"])
    assert (
        "force.csv: 2 row(s) whose field 'grams' is not a finite number skipped: lines 5, 9" in text
    )


def test_readings_beyond_capacity_are_reported_and_their_frames_invalid(tmp_path):
    tl = Timeline(presses=2)
    raw = write_reference_raw(tmp_path / "ref", tl)
    lines = (raw / "force_log.txt").read_text().split("\n")
    spike = 100  # a reading in the middle of the recording
    t_spike = float(lines[spike - 1].split(",")[0]) - T0_UNIX
    _replace_field(raw / "force_log.txt", spike, 1, "9000.00")  # 88 N on a 50 N scale
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    warning = next(w for w in qa["warnings"] if "capacity" in w)
    assert (
        f"force_log.txt line {spike}: force 88.3 N is beyond the scale's capacity (50 N" in warning
    )
    assert qa["plausibility"]["readings_over_capacity"] == 1
    assert qa["invalid_frames"]["force_over_capacity"] >= 1
    assert qa["force_n"]["max"] < 10
    with open_dataset(tmp_path / "d.h5") as ds:
        near = np.abs(ds.timestamp_s - T0_UNIX - t_spike) < 0.5 / tl.scale_hz
        assert near.any() and not ds.valid[near].any()
    bigger = ProcessConfig(image_size=32, workers=2, scale_capacity_n=100.0)
    qa = process_recording(raw, tmp_path / "d2.h5", bigger, progress=False)
    assert not any("capacity" in w for w in qa["warnings"])


def test_timestamps_going_backwards_are_reported(tmp_path):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=1))
    rows = (raw / "force.csv").read_text().split("\n")
    rows[20], rows[21] = rows[21], rows[20]  # lines 21 and 22 swapped
    (raw / "force.csv").write_text("\n".join(rows))
    rows = (raw / "printer.csv").read_text().split("\n")
    rows[3], rows[4] = rows[4], rows[3]
    (raw / "printer.csv").write_text("\n".join(rows))
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    text = "\n".join(qa["warnings"])
    assert "force.csv line 22: force reading time t_mono goes backwards" in text
    assert "printer.csv line 5: printer command time t_mono goes backwards" in text


# --- item 15 for process: no silent overwrite -------------------------------------------------
def test_process_refuses_to_overwrite(tmp_path, capsys):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=1))
    force_log = raw / "force.csv"
    before = force_log.read_bytes()
    for overwrite in (False, True):  # a file of the recording: never
        with pytest.raises(OutputExistsError, match=r"force\.csv: is a file of the raw recording"):
            process_recording(raw, force_log, SMALL, progress=False, overwrite=overwrite)
    code = main(["process", str(raw), "--out", str(force_log), "--overwrite", "--no-progress"])
    assert code == 1 and "is a file of the raw recording" in capsys.readouterr().err
    assert force_log.read_bytes() == before
    other = tmp_path / "notes.txt"
    other.write_text("keep me")
    code = main(["process", str(raw), "--out", str(other), "--no-progress"])
    assert code == 1 and "already exists" in capsys.readouterr().err
    assert other.read_text() == "keep me"
    code = main(
        [
            "process",
            str(raw),
            "--out",
            str(other),
            "--image-size",
            "32",
            "--overwrite",
            "--no-progress",
        ]
    )
    assert code == 0
    with open_dataset(other) as ds:
        assert ds.image_size == 32
