"""Live recordings on a real full disk (a 256 KiB tmpfs), and never replacing a file."""

from __future__ import annotations

import hashlib
import json
import os
import time
import urllib.request
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import run_beadsight
from helpers.live import (
    BACKEND,
    SPAN,
    TINY,
    TORCH,
    ScriptedSource,
    live_sim_args,
    press_frames,
    wait_until,
)

from beadsight.cli import main
from beadsight.files import OutputExistsError, WriteError
from beadsight.geometry import total_force_n
from beadsight.live.outputs.viewer.server import ViewerServer
from beadsight.live.recording.readings import ReadingsWriter, open_readings
from beadsight.live.sensor import LiveSensor

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads


@pytest.fixture(scope="module")
def presses():
    return press_frames(presses=4, per_press=30)  # 120 frames: 106 maps of 16 KiB


def record(model, frames, path: Path, **options):
    """Run a sensor over ``frames`` recording to ``path``; (updates, error, recorder error)."""
    seen, failures = [], []
    sensor = LiveSensor(model, ScriptedSource(frames), **BACKEND).open()
    sensor.on_update(seen.append)
    sensor.start_recording(path, on_error=failures.append, **options)
    with sensor:
        assert sensor.wait(60)
        with pytest.raises(WriteError) as info:
            sensor.stop_recording()
    return seen, info.value, failures


def test_hdf5_recording_on_a_full_disk_stops_and_keeps_what_it_wrote(model, presses, full_disk):
    frames, _ = presses
    path = full_disk / "rec.h5"
    seen, error, failures = record(model, frames, path)
    assert failures == [error]  # reported when it happened, raised by stop_recording
    assert str(path) in str(error) and "disk full" in str(error)
    assert not path.exists()  # never renamed to its final name
    partial = full_disk / "rec.h5.partial"
    assert f"readings before it are in {partial}" in str(error)
    with open_readings(partial) as rf:
        n = len(rf)
        assert 1 <= n < len(seen)
        for i in range(n):  # what was written is whole: the maps are the readings' maps
            np.testing.assert_array_equal(rf.pressure_kpa[i], seen[i].reading.pressure_kpa)
        np.testing.assert_array_equal(rf.timestamp_s, [u.reading.timestamp_s for u in seen[:n]])
    assert f"the {n} readings" in str(error)


def test_mcap_recording_on_a_full_disk_stops_and_keeps_what_it_wrote(model, presses, full_disk):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    frames, _ = presses
    path = full_disk / "rec.mcap"
    seen, error, _ = record(model, frames, path)
    assert str(path) in str(error) and "disk full" in str(error)
    assert not path.exists()
    with open(full_disk / "rec.mcap.partial", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        maps = [
            np.frombuffer(bytes(msg.data), "<f4").reshape(64, 64)
            for _s, _c, _m, msg in reader.iter_decoded_messages(topics=["/beadsight/pressure"])
        ]
    assert 1 <= len(maps) < len(seen)
    assert f"the {len(maps)} readings" in str(error)
    for got, update in zip(maps, seen, strict=False):
        np.testing.assert_array_equal(got, update.reading.pressure_kpa)


def test_a_write_that_fails_anyway_keeps_only_whole_readings(presses, full_disk, monkeypatch):
    """Another program fills the disk after the writer looked: the write itself fails."""
    monkeypatch.setattr(ReadingsWriter, "_room", lambda self: 1 << 40)
    rng = np.random.default_rng(0)
    small = TINY.with_image_size(32)  # 4 KiB maps: a batch of 32 fits, the next does not
    path = full_disk / "rec.h5"
    written = []
    writer = ReadingsWriter(path, small)
    with pytest.raises(WriteError, match=r"rec\.h5: disk full"):
        for i in range(1000):
            reading = _Reading(rng.uniform(1, 100, (32, 32)).astype(np.float32), i)
            written.append(reading)
            writer.append(reading)
    with pytest.raises(WriteError):
        writer.close()  # the same error again; nothing renamed
    assert not path.exists()
    with open_readings(full_disk / "rec.h5.partial") as rf:
        assert 1 <= len(rf) < len(written)
        for i in range(len(rf)):  # no zero-filled rows claimed as readings
            np.testing.assert_array_equal(rf.pressure_kpa[i], written[i].pressure_kpa)


def test_an_mcap_write_that_fails_anyway_ends_the_file_after_whole_chunks(full_disk, monkeypatch):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    import beadsight.live.recording.mcap as mcap_module

    monkeypatch.setattr(mcap_module.McapReadingsWriter, "_room", lambda self: 1 << 40)
    monkeypatch.setattr(mcap_module, "CHUNK_BYTES", 48 * 1024)  # chunks of 3 readings
    rng = np.random.default_rng(0)
    path = full_disk / "rec.mcap"
    written = []
    writer = mcap_module.McapReadingsWriter(path, TINY)
    with pytest.raises(WriteError, match=r"rec\.mcap: disk full.*may be damaged"):
        for i in range(1000):
            reading = _Reading(rng.uniform(1, 100, (64, 64)).astype(np.float32), i)
            written.append(reading)
            writer.append(reading)
    assert not path.exists()
    with open(full_disk / "rec.mcap.partial", "rb") as f:  # readers take the file as it is
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        maps = [
            np.frombuffer(bytes(msg.data), "<f4").reshape(64, 64)
            for _s, _c, _m, msg in reader.iter_decoded_messages(topics=["/beadsight/pressure"])
        ]
    assert 3 <= len(maps) < len(written)
    for got, reading in zip(maps, written, strict=False):
        np.testing.assert_array_equal(got, reading.pressure_kpa)


class _Reading:
    def __init__(self, kpa: np.ndarray, i: int):
        self.pressure_kpa, self.frame_index = kpa, i
        self.force_n, self.cop_mm, self.has_contact = float(kpa.sum()), np.zeros(2), True
        self.contact_area_mm2, self.timestamp_s, self.latency_s = 1.0, 1.7e9 + i, 0.01


def test_cli_live_output_on_a_full_disk_exits_non_zero(model, full_disk, tmp_path):
    checkpoint = model.save(tmp_path / "tiny.pt")
    out = full_disk / "readings.h5"
    start = time.monotonic()
    done = run_beadsight(*live_sim_args(checkpoint), "--output", out, "--duration", "60")
    assert done.returncode == 1, (done.stdout, done.stderr)
    assert time.monotonic() - start < 40  # stopped by the failure, not by --duration
    err = done.stderr.strip().splitlines()[-1]
    assert str(out) in err and "disk full" in err
    assert "wrote" not in done.stdout
    assert not out.exists()
    with open_readings(full_disk / "readings.h5.partial") as rf:
        assert len(rf) >= 1
        for i in range(len(rf)):  # each map is whole: its integral is the recorded force
            force = float(total_force_n(rf.pressure_kpa[i], rf.geometry))
            assert force == pytest.approx(float(rf.force_n[i]), rel=1e-4, abs=1e-6)


def test_viewer_record_button_on_a_full_disk_shows_the_error(model, presses, full_disk):
    frames, _ = presses  # ~100 maps recorded after the click: six times the 256 KiB disk
    source = ScriptedSource(frames, stall_after=SPAN + 5)
    with (
        LiveSensor(model, source, **BACKEND) as sensor,
        ViewerServer(sensor, port=0, record_dir=full_disk) as viewer,
    ):
        wait_until(lambda: sensor.stats().readings >= 5, 30, "readings")
        assert _post(viewer.url + "api/record", {"action": "start"})["recording"]
        source.release.set()
        wait_until(lambda: sensor.recording_error is not None, 30, "the disk to fill up")
        state = json.loads(urllib.request.urlopen(viewer.url + "api/state").read())
        assert state["recording"] is None
        assert "disk full" in state["record_error"] and "beadsight-" in state["record_error"]
        assert sensor.wait(60)
        with pytest.raises(WriteError, match="disk full"):  # and Python code is told too
            sensor.stop_recording()
    assert list(full_disk.glob("beadsight-*.h5")) == []  # nothing under a final name
    (partial,) = full_disk.glob("beadsight-*.h5.partial")
    with open_readings(partial) as rf:
        assert len(rf) >= 1


def _post(url: str, body: dict) -> dict:
    request = urllib.request.Request(
        url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"}
    )
    return json.loads(urllib.request.urlopen(request).read())


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_cli_live_output_refuses_an_existing_dataset(model, make_dataset, tmp_path, capsys):
    dataset = make_dataset()
    before = _digest(dataset)
    checkpoint = model.save(tmp_path / "tiny.pt")
    command = [
        *live_sim_args(checkpoint),
        "--frames",
        "3",
        "--output",
        str(dataset),
    ]
    assert main(command) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(dataset) in err[0] and "--overwrite" in err[0]
    assert _digest(dataset) == before
    assert main([*command, "--overwrite"]) == 0
    with open_readings(dataset) as rf:  # replaced only once the recording was complete
        assert len(rf) == 3


def test_an_unfinished_recording_is_not_replaced(model, tmp_path):
    partial = tmp_path / "r.h5.partial"
    partial.write_bytes(b"readings of a crashed run")
    sensor = LiveSensor(model, "sim", **BACKEND).open()
    try:
        with pytest.raises(OutputExistsError, match=r"r\.h5\.partial.*did not finish"):
            sensor.start_recording(tmp_path / "r.h5")
    finally:
        sensor.stop()
    assert partial.read_bytes() == b"readings of a crashed run"


def test_record_presses_in_the_same_second_make_new_files(model, tmp_path):
    """Two Record presses within one second each get their own file; nothing is replaced."""
    starts = []
    with (
        LiveSensor(model, "sim", replace(TORCH, source_fps=30)) as sensor,
        ViewerServer(sensor, port=0, record_dir=tmp_path) as viewer,
    ):
        wait_until(lambda: sensor.stats().readings >= 1, 30, "a reading")
        stamp = time.strftime("beadsight-%Y%m%d-%H%M%S", time.localtime(time.time() + 1))
        taken = tmp_path / f"{stamp}.h5"  # the name a press in the next second would pick
        taken.write_bytes(b"an earlier recording")
        while time.strftime("%S") != stamp[-2:]:  # wait for that second to begin
            time.sleep(0.005)
        for _ in range(2):
            starts.append(_post(viewer.url + "api/record", {"action": "start"})["recording"])
            wait_until(lambda: sensor.recording[1] >= 3, 30, "3 readings recorded")
            _post(viewer.url + "api/record", {"action": "stop"})
    assert taken.read_bytes() == b"an earlier recording"
    first, second = (Path(rec["path"]) for rec in starts)
    assert first.name == f"{stamp}-2.h5"
    assert second not in (first, taken)
    if second.name.startswith(stamp):  # (unless the second press came a second later)
        assert second.name == f"{stamp}-3.h5"
    with open_readings(first) as a, open_readings(second) as b:
        assert len(a) >= 3 and len(b) >= 3
        assert b.timestamp_s[0] > a.timestamp_s[-1]  # two recordings, one after the other


def test_cli_live_on_a_disk_full_at_start_leaves_no_partial(model, presses, full_disk, capsys):
    """Issue 26 item 6: nothing recorded, so no (0-byte) ``.partial`` is left to refuse the
    next run."""
    from helpers.live import live_argv, write_video

    frames, _ = presses
    video = write_video(full_disk.parent / "v.avi", frames[:30], fps=60)
    checkpoint = model.save(full_disk.parent / "tiny.pt")
    filler = full_disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:  # fill the disk up to the last byte
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass
    finally:
        os.close(fd)
    out = full_disk / "rec.h5"
    more = ["--no-viewer", "--output", str(out), "--frames", "5", "--loop"]
    assert main(live_argv(checkpoint, video, *more)) == 1
    err = capsys.readouterr().err
    assert f"could not write {out}: disk full; nothing was recorded" in err
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]


def test_to_mcap_with_a_nan_timestamp_is_a_named_error_and_leaves_nothing(
    model, presses, tmp_path, capsys
):
    """Issue 26: a readings file with a NaN timestamp: one line naming the file and field,
    exit 1, and no ``.partial`` of the MCAP file."""
    import h5py

    frames, _ = presses
    path = tmp_path / "rec.h5"
    sensor = LiveSensor(model, ScriptedSource(frames[:40]), **BACKEND).open()
    sensor.start_recording(path)
    with sensor:
        assert sensor.wait(60)
        sensor.stop_recording()
    with h5py.File(path, "r+") as f:
        f["timestamp_s"][3] = np.nan
    out = tmp_path / "rec.mcap"
    assert main(["to-mcap", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"{path}: dataset 'timestamp_s' has 1 NaN/inf value(s) (first at reading 3)" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.h5"]
