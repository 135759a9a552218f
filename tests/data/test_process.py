"""Processing raw recordings into datasets: labels, streaming, QA, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.recording import (
    T0_UNIX,
    Timeline,
    frame_level,
    write_beadsight_raw,
    write_reference_raw,
)

from beadsight.cli import main
from beadsight.config import ConfigError
from beadsight.data.dataset import open_dataset
from beadsight.data.process.config import ProcessConfig
from beadsight.data.process.run import (
    hold_positions,
    interpolate_force,
    process_recording,
    qa_paths,
)
from beadsight.data.recording import RecordingError, open_recording

SMALL = ProcessConfig(image_size=32, workers=2, batch_frames=16)


# --- labels ---------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["pchip", "cubic", "linear"])
def test_force_interpolation_never_extrapolates(method):
    t = np.array([1.0, 1.1, 1.2, 1.3, 2.0, 2.1])
    f = 3.0 * t  # linear: every method reproduces it exactly
    frames = np.array([0.9, 1.0, 1.05, 1.25, 1.5, 2.05, 2.1, 2.2])
    force, reason = interpolate_force(t, f, frames, method=method, max_gap_s=0.5)
    np.testing.assert_array_equal(reason, [1, 0, 0, 0, 3, 0, 0, 2])
    ok = reason == 0
    np.testing.assert_allclose(force[ok], 3.0 * frames[ok], atol=1e-9)
    assert np.isnan(force[~ok]).all()


def test_pchip_does_not_overshoot_a_step():
    t = np.arange(10) * 0.1
    f = np.where(t >= 0.5, 10.0, 0.0)
    frames = np.linspace(0, 0.9, 200)
    pchip, _ = interpolate_force(t, f, frames, method="pchip")
    cubic, _ = interpolate_force(t, f, frames, method="cubic")
    assert pchip.min() >= 0 and pchip.max() <= 10
    assert cubic.min() < 0 or cubic.max() > 10  # the spline rings (why pchip is the default)


def test_force_duplicates_and_unsorted():
    t = np.array([2.0, 1.0, 1.0, 3.0])
    f = np.array([4.0, 1.0, 3.0, 6.0])
    force, reason = interpolate_force(t, f, np.array([1.0, 2.5]), method="linear", max_gap_s=2)
    np.testing.assert_allclose(force, [2.0, 5.0])  # duplicate times averaged
    assert (reason == 0).all()
    force, reason = interpolate_force(t[:1], f[:1], np.array([2.0]))
    assert reason[0] == 1 and np.isnan(force[0])


def test_zero_order_hold():
    t_moves = np.array([1.0, 2.0, 3.0, 4.0])
    xy = np.array([[np.nan, np.nan], [1.0, 2.0], [1.0, 2.0], [5.0, 6.0]])
    data = np.array([False, True, True, False])
    frames = np.array([0.5, 1.0, 1.5, 2.0, 2.9, 3.5, 4.0, 9.0])
    pos, reason = hold_positions(t_moves, xy, data, frames)
    np.testing.assert_array_equal(reason, [2, 3, 3, 0, 0, 0, 3, 3])
    np.testing.assert_array_equal(pos[3:6], [[1, 2]] * 3)
    assert np.isnan(pos[reason > 0]).all()
    _, reason = hold_positions(np.array([]), np.zeros((0, 2)), np.zeros(0, bool), frames)
    assert (reason == 1).all()


# --- whole recordings -------------------------------------------------------------------
def _check_dataset(out, tl: Timeline, qa: dict, n_frames: int, monotonic: bool):
    with open_dataset(out) as ds:
        assert len(ds) == n_frames
        assert ds.image_size == 32 and ds.channel_order == "RGB"
        # frame order: grey level encodes the frame number
        levels = ds.read_frames(0, len(ds)).reshape(len(ds), -1).mean(axis=1)
        times = ds.timestamp_s - T0_UNIX
        k = np.round(times * tl.fps).astype(int)
        np.testing.assert_allclose(levels, [frame_level(i) for i in k], atol=5)  # XVID: ~3
        truth_pos, truth_data = tl.position_at(times)
        valid = ds.valid
        assert valid.sum() > 0.6 * len(ds)
        np.testing.assert_allclose(ds.force_n[valid], tl.force_n(times[valid]), atol=0.35)
        np.testing.assert_allclose(ds.position_mm[valid], truth_pos[valid], atol=1e-9)
        assert not valid[~truth_data].any()  # no frame valid outside data moves
        assert not valid[times < tl.force_start_s].any()  # nor before the force log
        assert ds.num_presses == tl.presses
    assert qa["presses"] == tl.presses
    assert qa["frames_written"] == n_frames
    assert qa["invalid_frames"]["before_force_log"] == int((tl.frame_times() < 0.1).sum())
    assert qa["invalid_frames"]["non_data_move"] > 0
    assert qa["clock"] == ("monotonic" if monotonic else "unix")
    json_path, png_path = qa_paths(out)
    assert json.loads(json_path.read_text())["presses"] == tl.presses
    assert png_path.read_bytes()[:4] == b"\x89PNG"


def test_process_beadsight_recording(tmp_path):
    tl = Timeline(presses=3)
    raw = write_beadsight_raw(tmp_path / "raw", tl, drop_frames=(40, 41))
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    n = len(tl.frame_times()) - 2
    _check_dataset(tmp_path / "d.h5", tl, qa, n, monotonic=True)
    assert qa["dropped_frames"]["camera_index_gaps"] == 2
    assert qa["dropped_frames"]["time_gaps"] == 2
    assert qa["decode_scale"] == 1  # 96x120 raw frames: no room to decode smaller
    assert qa["force_n"]["max"] == pytest.approx(12.0, abs=0.1)


def test_process_reference_recording_xvid(tmp_path):
    tl = Timeline(presses=2)
    raw = write_reference_raw(tmp_path / "ref", tl)
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    _check_dataset(tmp_path / "d.h5", tl, qa, len(tl.frame_times()), monotonic=False)
    assert qa["raw_format"] == "reference-raw"


def test_process_reduced_decoding_for_large_frames(tmp_path):
    tl = Timeline(presses=1)
    raw = write_beadsight_raw(tmp_path / "raw", tl, frame_hw=(256, 320))
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    assert qa["decode_scale"] == 4  # the 188 px crop still covers 32 px at 1/4 scale
    with open_dataset(tmp_path / "d.h5") as ds:
        levels = ds.read_frames(0, 20).reshape(20, -1).mean(axis=1)
    np.testing.assert_allclose(levels, [frame_level(i) for i in range(20)], atol=3)


def test_process_tolerates_truncated_chunk(tmp_path):
    tl = Timeline(presses=2)
    raw = write_beadsight_raw(tmp_path / "raw", tl, chunk_frames=40)
    last = max(open_recording(raw).videos.items())[1]
    data = last.read_bytes()
    last.write_bytes(data[: len(data) // 2])
    qa = process_recording(raw, tmp_path / "d.h5", SMALL, progress=False)
    missing = qa["dropped_frames"]["missing_from_video"] + qa["dropped_frames"]["undecodable"]
    assert qa["dropped_frames"]["missing_from_video"] > 0
    assert qa["frames_written"] == len(tl.frame_times()) - missing
    assert any("missing from the video" in w for w in qa["warnings"])
    with open_dataset(tmp_path / "d.h5") as ds:
        assert len(ds) == qa["frames_written"]


def test_process_config_and_input_errors(tmp_path):
    with pytest.raises(ConfigError, match="force_interpolation"):
        ProcessConfig(force_interpolation="spline")
    with pytest.raises(ConfigError, match="decode_scale"):
        ProcessConfig(decode_scale=3)
    with pytest.raises(RecordingError, match="not a raw recording"):
        (tmp_path / "empty").mkdir()
        process_recording(tmp_path / "empty", tmp_path / "d.h5", SMALL, progress=False)


def test_cli_process(tmp_path, capsys):
    raw = write_beadsight_raw(tmp_path / "raw", Timeline(presses=2))
    out = tmp_path / "d.h5"
    code = main(
        [
            "process",
            str(raw),
            "--out",
            str(out),
            "--image-size",
            "32",
            "--force-interpolation",
            "cubic",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "2 presses" in text and str(out) in text
    with open_dataset(out) as ds:
        assert ds.provenance["process"]["force_interpolation"] == "cubic"
    code = main(["process", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.h5")])
    assert code == 1
    assert "raw recording folder not found" in capsys.readouterr().err
