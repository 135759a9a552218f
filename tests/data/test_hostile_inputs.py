"""Issue 26: hostile raw recordings for ``process`` -- a named error, never a hang, an
unbounded read or a leftover ``.partial``."""

from __future__ import annotations

import pytest
from helpers.recording import Timeline, write_beadsight_raw

from beadsight.cli import main
from beadsight.data.process import ProcessConfig, process_recording
from beadsight.data.recording import RecordingError

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
