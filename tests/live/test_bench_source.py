"""``beadsight bench live --source``: the live loop's rate and the camera's truth, from a
real video file read through OpenCV and from the simulator."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.live import TORCH, press_frames, tiny_model, write_video

from beadsight.cli import main
from beadsight.live.bench import bench_source

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads


def test_duplicated_frames_of_a_video_file_are_counted(tmp_path):
    frames, _ = press_frames(presses=1, per_press=30)
    repeated = np.arange(3, len(frames), 4)  # every 4th frame repeats the one before it
    frames[repeated] = frames[repeated - 1]
    video = write_video(tmp_path / "dup.avi", frames, fps=120)
    stats = bench_source(tiny_model(), str(video), 30.0, TORCH)
    assert stats.frames == len(frames)
    assert stats.camera_duplicated == len(repeated)
    assert stats.camera_dropped == 0


def test_bench_live_source_cli_prints_the_camera_truth(capsys):
    argv = ["bench", "live", "--source", "sim", "--duration", "2.5", "--json", "--backend", "torch"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["source"] == "sim" and result["requested_fps"] == 30.0
    assert result["readings"] > 0 and result["camera_duplicated"] == 0
    assert 20 < result["camera_fps"] < 40 and result["camera_slow"] is False


def test_bench_live_source_refuses_the_predictor_only_flags(capsys):
    assert main(["bench", "live", "--source", "sim", "--rate", "30"]) == 1
    assert "--duration" in capsys.readouterr().err
